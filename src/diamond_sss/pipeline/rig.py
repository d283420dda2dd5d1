"""The generation lattice of a capture that has no lattice: the cameras and lights the diffusion stages target.

A capture of only its sparse images (what a user brings) declares no camera and no light beyond its own, so the
lattice-aware stages would find nothing to generate. Its lattice is made here instead, either

* sampled: ``count`` cameras placed where the real ones could be (on their distance band from the object's
  centre, in their elevation band widened by :data:`ELEVATION_MARGIN_DEG`, aimed at the centre, upright, with the
  distance and image size of the nearest real camera and its intrinsics, or framed as the priors' training cameras
  (:func:`framed_intrinsics`: a zoom on the object)), spread by farthest-point sampling away from the real
  views; lights the same way on the real lights' band, with the nearest real light's distance and intensity; or
* read from a rig file: a light stage's full layout, a transforms file with top-level ``cameras`` and ``lights``
  (:func:`~diamond_sss.data.transforms.parse_rig`); its cameras and lights at a real one's place are that one.

A capture with a lattice keeps it, its cameras without an image framed as the priors' when asked
(:func:`framed_capture_lattice`).

Either way the lattice is written as ``<folder>/transforms_lattice.json``: the real cameras and lights first
(their indices are the capture's), the new ones after, and the real images of the regime as its frames, so that
every stage reads it as it reads a capture with a lattice. Elevation is measured from the mean of the real
cameras' up vectors (world +Z where they disagree), angles in degrees, distances in scene units.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    intrinsics_matrix,
    look_at_opengl_c2w,
    mean_up_vector,
    opencv_w2c_to_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_ray_directions,
    project_points,
    world_to_camera,
)
from diamond_sss.data.dataset import Camera, OLATDataset, directions_from
from diamond_sss.data.transforms import parse_rig
from diamond_sss.diffusion.nvs.canonical import PRIOR_FRAME_FILL
from diamond_sss.errors import DataError
from diamond_sss.utils.io import atomic_write_json

logger = logging.getLogger(__name__)

ELEVATION_MARGIN_DEG = 15.0
"""How far beyond the real cameras' (lights') elevation band sampled cameras (lights) may lie, in degrees."""

CANDIDATES = 4096
"""Directions on a Fibonacci sphere among which the sampled cameras and lights are chosen."""

RIG_FRAMINGS = ("real", "prior")
"""How placed cameras frame the object: as the nearest real camera does, or as the priors' training cameras did."""

LATTICE_SPLIT = "lattice"
"""The split name of the written lattice (``transforms_lattice.json``)."""


@dataclass(frozen=True)
class LatticeSource:
    """Where the generation lattice is read from: ``OLATDataset(data, split)``; ``new_views`` / ``new_lights``:
    the indices that no real image has (after the capture's own)."""

    data: Path
    split: str
    new_views: tuple[int, ...] = ()
    new_lights: tuple[int, ...] = ()


def elevation_deg(directions: Tensor, up: Tensor) -> Tensor:
    """Elevation ``asin(d . up)`` of unit ``directions [N,3]`` above the plane normal to ``up``, degrees ``[N]``."""
    return torch.rad2deg(torch.asin((directions.double() @ up.double()).clamp(-1.0, 1.0)))


def fibonacci_sphere(count: int) -> Tensor:
    """``count`` near-uniform unit directions ``[count,3]`` (float64): ``z_k = 1 - (2k + 1) / count``, azimuth
    ``k`` golden angles."""
    k = torch.arange(count, dtype=torch.float64)
    z = 1.0 - (2.0 * k + 1.0) / count
    rho = (1.0 - z**2).clamp_min(0.0).sqrt()
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([rho * phi.cos(), rho * phi.sin(), z], dim=-1)


def spread_away(candidates: Tensor, fixed: Tensor, count: int) -> list[int]:
    """Greedy farthest-point sampling of ``count`` rows of ``candidates [M,3]`` away from the ``fixed [N,3]`` rows
    and from each other: each pick maximises the smallest Euclidean distance to what is fixed or picked; ties go to
    the lowest index. Deterministic."""
    count = min(count, candidates.shape[0])
    if count <= 0:
        return []
    nearest = torch.full((candidates.shape[0],), math.inf, dtype=candidates.dtype)
    if fixed.shape[0]:
        nearest = torch.cdist(candidates, fixed.to(candidates)).amin(dim=1)
    chosen: list[int] = []
    for _ in range(count):
        pick = int(torch.argmax(nearest))
        chosen.append(pick)
        nearest = torch.minimum(nearest, (candidates - candidates[pick]).norm(dim=-1))
        nearest[pick] = -1.0
    return chosen


def place_directions(real: Tensor, up: Tensor, count: int, margin_deg: float = ELEVATION_MARGIN_DEG,
                     max_angle_deg: float = 0.0) -> tuple[Tensor, Tensor]:
    """``count`` unit directions in the elevation band of the unit ``real [N,3]`` directions widened by
    ``margin_deg`` (clipped to +-90), within ``max_angle_deg`` of the nearest real direction (0: anywhere), spread
    away from them (:func:`spread_away` over :data:`CANDIDATES`), and for each the index of its angularly nearest
    real direction: ``([count,3], [count])``."""
    elevations = elevation_deg(real, up)
    low = max(-90.0, float(elevations.min()) - margin_deg)
    high = min(90.0, float(elevations.max()) + margin_deg)
    candidates = fibonacci_sphere(CANDIDATES)
    candidate_elevations = elevation_deg(candidates, up)
    keep = (candidate_elevations >= low) & (candidate_elevations <= high)
    if max_angle_deg > 0.0:
        keep &= (candidates @ real.double().T).amax(dim=1) >= math.cos(math.radians(max_angle_deg))
    candidates = candidates[keep]
    placed = candidates[spread_away(candidates, real.double(), count)]
    nearest = torch.argmax(placed @ real.double().T, dim=1) if len(placed) else torch.zeros(0, dtype=torch.long)
    return placed, nearest


def camera_entry(capture: OLATDataset, view: int, c2w: Tensor | None = None) -> dict:
    """The ``cameras`` entry of view ``view`` of ``capture`` (intrinsics in pixels of its images), with another
    OpenGL camera-to-world ``c2w`` when given."""
    camera = capture.cameras[view]
    pose = opencv_w2c_to_opengl_c2w(camera.w2c.double()) if c2w is None else c2w.double()
    return {"transform_matrix": pose.tolist(), "fl_x": float(camera.K[0, 0]), "fl_y": float(camera.K[1, 1]),
            "cx": float(camera.K[0, 2]), "cy": float(camera.K[1, 2]), "w": camera.width, "h": camera.height}


def light_entry(position: Tensor, intensity: Tensor) -> dict:
    return {"position": position.double().tolist(), "intensity": intensity.double().tolist()}


def silhouette_radius(capture: OLATDataset, observations: Sequence[int], center: Tensor) -> float:
    """Radius (scene units) of the sphere about ``center`` that the silhouettes of ``observations`` span: the largest
    ``d sin(alpha)`` over their views, ``d`` the camera's distance from ``center`` and ``alpha`` the widest angle
    between the ray to ``center`` and a ray through a pixel of the view's masks (> 0.5, united over its images). A
    :class:`DataError` names the capture when every mask is empty; a mask that touches its image's border (the
    object cut off, so its radius is only a lower bound there) is named in a warning."""
    center = center.double()
    masks: dict[int, Tensor] = {}
    for index in observations:
        view = capture.observations[index].view
        inside = capture.load(index).mask[..., 0] > 0.5
        masks[view] = masks[view] | inside if view in masks else inside
    radius = 0.0
    for view, inside in masks.items():
        if not bool(inside.any()):
            continue
        if bool(inside[0].any() or inside[-1].any() or inside[:, 0].any() or inside[:, -1].any()):
            logger.warning("%s: view %d's mask touches the image border: the object is cut off there, so the "
                           "framed cameras (rig_framing=prior) may crop it", capture.json_path, view)
        camera = capture.cameras[view]
        eye = camera_centers(camera.w2c.double())
        axis = (center - eye) / (center - eye).norm()
        rays = pixel_ray_directions(camera.w2c.double(), camera.K.double(), camera.height, camera.width)[inside]
        alpha = math.acos(max(-1.0, min(1.0, float((rays @ axis).min()))))
        radius = max(radius, float((center - eye).norm()) * math.sin(min(alpha, math.pi / 2)))
    if radius <= 0.0:
        raise DataError(f"{capture.json_path}: every mask of the {len(observations)} images is empty: no object to "
                        "frame the generated cameras on (rig_framing=prior); give masks or use rig_framing=real")
    return radius


def framed_intrinsics(center: Tensor, radius: float, width: int, height: int, fill: float = PRIOR_FRAME_FILL
                      ) -> Tensor:
    """``K [3,3]`` (float64) in which a sphere of ``radius`` about ``center`` (camera space, OpenCV, ``z > 0``) spans
    ``fill`` of the shorter half-side around the image's centre, where its centre projects:
    ``f = fill min(W, H) / 2 / tan(asin(radius / |c|))``, ``(cx, cy) = (W, H) / 2 - f (c_x, c_y) / c_z``."""
    center = center.double()
    distance = float(center.norm())
    if not (0.0 < radius < distance and float(center[2]) > 0.0):
        raise ValueError(f"need 0 < radius < distance with the centre in front, got radius {radius} about "
                         f"{center.tolist()}")
    focal = fill * 0.5 * min(width, height) / math.tan(math.asin(radius / distance))
    shift = focal * center[:2] / center[2]
    return intrinsics_matrix(focal, focal, 0.5 * width - float(shift[0]), 0.5 * height - float(shift[1])).double()


def framed_camera_intrinsics(camera: Camera, center: Tensor, radius: float) -> Tensor:
    """:func:`framed_intrinsics` of ``camera`` (its pose and image size) for the object's sphere of ``radius`` about
    world ``center``, the radius capped below the camera's distance."""
    center_cam = world_to_camera(center[None].double(), camera.w2c.double())[0]
    return framed_intrinsics(center_cam, min(radius, 0.99 * float(center_cam.norm())), camera.width, camera.height)


def sampled_rig(capture: OLATDataset, views: int, lights: int, max_view_angle_deg: float = 0.0,
                framing: str = "real", observations: Sequence[int] = ()) -> tuple[list[dict], list[dict]]:
    """``views`` new cameras (each within ``max_view_angle_deg`` of a real one; 0: anywhere) and ``lights`` new
    lights around ``capture`` (full resolution), as ``cameras`` / ``lights`` entries (see the module docstring).
    ``framing="prior"`` gives each new camera the focal length and centred principal point in which the object
    (:func:`silhouette_radius` of ``observations``) fills its image as the priors' training cameras framed theirs
    (:data:`~diamond_sss.diffusion.nvs.canonical.PRIOR_FRAME_FILL`); ``"real"`` the nearest real camera's."""
    if framing not in RIG_FRAMINGS:
        raise ValueError(f"framing must be one of {RIG_FRAMINGS}, got {framing!r}")
    center = capture.bounds.center.double()
    up = mean_up_vector(capture.viewmats)
    centers = capture.camera_centers.double()
    real_dirs = directions_from(centers, center).double()
    directions, nearest = place_directions(real_dirs, up, views, max_angle_deg=max_view_angle_deg)
    radius = silhouette_radius(capture, observations, center) if framing == "prior" and views else None
    cameras = []
    for direction, source in zip(directions, nearest.tolist()):
        distance = float((centers[source] - center).norm())
        entry = camera_entry(capture, source, look_at_opengl_c2w(center + distance * direction, center, up))
        if radius is not None:
            K = framed_intrinsics(torch.tensor([0.0, 0.0, distance]), min(radius, 0.99 * distance), entry["w"],
                                  entry["h"])
            entry.update(_intrinsics_entry(K))
        cameras.append(entry)
    positions = capture.light_positions.double()
    light_dirs = directions_from(positions, center).double()
    directions, nearest = place_directions(light_dirs, up, lights)
    new_lights = [light_entry(center + float((positions[source] - center).norm()) * direction,
                              capture.lights[source].intensity)
                  for direction, source in zip(directions, nearest.tolist())]
    return cameras, new_lights


def rig_from_file(path: Path, capture: OLATDataset) -> tuple[list[dict], list[dict]]:
    """The cameras and lights of the rig file ``path`` that are not the real ones of ``capture`` (full resolution),
    as ``cameras`` / ``lights`` entries; a camera at a real camera's place must have its intrinsics and image
    size, every camera the capture's image size (else a :class:`DataError` naming the file, entry and values)."""
    declared_cameras, declared_lights = parse_rig(path)
    meta = json.loads(path.read_text())
    scale = max(capture.bounds.radius, 1e-6)
    centers = capture.camera_centers.double()
    real_K = capture.intrinsics.double()
    cameras = []
    for camera, entry in zip(declared_cameras, meta["cameras"]):
        where = f"rig {path}: cameras[{camera.index}]"
        size = (camera.width or capture.width, camera.height or capture.height)
        if size != (capture.width, capture.height):
            raise DataError(f"{where}: image size {size[0]}x{size[1]} (w/h) contradicts the capture's "
                            f"{capture.width}x{capture.height} images ({capture.json_path})")
        position = torch.from_numpy(camera.c2w[:3, 3]).double()
        distance = (centers - position).norm(dim=-1)
        if float(distance.min()) <= 1e-3 * scale:
            view = int(torch.argmin(distance))
            K = _entry_intrinsics(entry, meta, capture.width, capture.height)
            if not torch.allclose(K, real_K[view], rtol=1e-2, atol=0.5):
                raise DataError(f"{where}: at view {view}'s place but its intrinsics (fx, fy, cx, cy) "
                                f"{_four(K)} contradict the capture's {_four(real_K[view])} ({capture.json_path})")
            continue
        cameras.append({**{key: entry[key] for key in entry if key not in ("file_path", "file_paths")},
                        "w": size[0], "h": size[1], **_fov_entry(entry, meta)})
    positions = capture.light_positions.double()
    lights = []
    for light in declared_lights:
        position = torch.from_numpy(light.position).double()
        if float((positions - position).norm(dim=-1).min()) > 1e-3 * max(float(positions.norm(dim=-1).max()), 1e-6):
            lights.append(light_entry(position, torch.from_numpy(light.intensity)))
    return cameras, lights


def _fov_entry(entry: dict, meta: dict) -> dict:
    """The file-level field of view of a rig camera that gives none of its own (entries are written alone)."""
    if any(key in entry for key in ("fl_x", "camera_angle_x")):
        return {}
    return {key: meta[key] for key in ("fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y")
            if key in meta}


def _entry_intrinsics(entry: dict, meta: dict, width: int, height: int) -> Tensor:
    """``K [3,3]`` of a rig ``cameras`` entry in pixels of ``width x height``."""
    merged = {**meta, **entry}
    if "fl_x" in merged:
        fx = float(merged["fl_x"])
        return intrinsics_matrix(fx, float(merged.get("fl_y", fx)), float(merged.get("cx", 0.5 * width)),
                                 float(merged.get("cy", 0.5 * height))).double()
    return intrinsics_from_fov(float(merged["camera_angle_x"]), width, height,
                               merged.get("camera_angle_y")).double()


def _four(K: Tensor) -> str:
    return "(" + ", ".join(f"{float(v):.2f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])) + ")"


def _intrinsics_entry(K: Tensor) -> dict:
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def write_lattice(folder: Path, capture: OLATDataset, observations: Sequence[int], cameras: list[dict],
                  lights: list[dict], intrinsics: dict[int, Tensor] | None = None) -> Path:
    """``folder/transforms_lattice.json``: the real cameras and lights of ``capture`` (full resolution; view ``v`` of
    ``intrinsics`` with ``K = intrinsics[v]``), then ``cameras`` and ``lights``, and the real ``observations`` as its
    frames (absolute paths)."""
    header = [camera_entry(capture, view) for view in range(capture.num_views)]
    for view, K in (intrinsics or {}).items():
        header[view].update(_intrinsics_entry(K))
    frames = []
    for index in observations:
        obs = capture.observations[index]
        light = capture.lights[obs.light]
        frame = {**{key: header[obs.view][key] for key in ("transform_matrix", "fl_x", "fl_y", "cx", "cy")},
                 "file_path": str(obs.image_path), "pl_pos": light.position.double().tolist(),
                 "pl_intensity": light.intensity.double().tolist()}
        if obs.mask_path is not None:
            frame["mask_path"] = str(obs.mask_path)
        frames.append(frame)
    payload = {"w": capture.width, "h": capture.height,
               "cameras": header + cameras,
               "lights": [light_entry(light.position, light.intensity) for light in capture.lights] + lights,
               "frames": frames}
    if capture.premultiplied_alpha is not None:
        payload["premultiplied_alpha"] = capture.premultiplied_alpha
    return atomic_write_json(Path(folder) / f"transforms_{LATTICE_SPLIT}.json", payload)


def check_cameras(cameras: list[dict], capture: OLATDataset, source: str) -> None:
    """A :class:`DataError` when a new camera (a ``cameras`` entry) cannot see the object of ``capture`` (its
    bounding sphere's centre behind the camera or outside its image), naming ``source`` (the rig file, or how the
    cameras were placed)."""
    center = capture.bounds.center.double()
    for index, entry in enumerate(cameras):
        w2c = opengl_c2w_to_opencv_w2c(torch.tensor(entry["transform_matrix"], dtype=torch.float64))
        K = _entry_intrinsics(entry, {}, entry["w"], entry["h"])
        uv, depth = project_points(center[None], w2c, K)
        u, v, z = float(uv[0, 0]), float(uv[0, 1]), float(depth[0])
        if not (z > 0.0 and 0.0 <= u <= entry["w"] and 0.0 <= v <= entry["h"]):
            view = capture.num_views + index
            raise DataError(f"{source}: new camera {index} (lattice view {view}) cannot see the object: its centre "
                            f"{[round(x, 4) for x in center.tolist()]} projects to ({u:.1f}, {v:.1f}) at depth "
                            f"{z:.3f}, outside the {entry['w']}x{entry['h']} image or behind the camera")


def framed_capture_lattice(folder: Path, data: Path, split: str, observations: Sequence[int],
                           downscale: float = 1.0) -> tuple[LatticeSource, OLATDataset]:
    """The lattice of capture ``data`` [``split``] written into ``folder`` with every camera that no image of
    ``observations`` has framed as the priors' training cameras (:func:`framed_intrinsics` of the
    :func:`silhouette_radius`; same pose and size), read back at ``downscale``; the cameras with an image, the lights
    and the images as they are."""
    capture = OLATDataset(data, split)
    center = capture.bounds.center.double()
    radius = silhouette_radius(capture, observations, center)
    seen = {capture.observations[index].view for index in observations}
    framed = {view: framed_camera_intrinsics(capture.cameras[view], center, radius)
              for view in sorted(set(range(capture.num_views)) - seen)}
    write_lattice(folder, capture, observations, [], [], intrinsics=framed)
    logger.info("generation lattice %s: the capture's %d cameras without an image framed as the priors'",
                folder, len(framed))
    return LatticeSource(Path(folder), LATTICE_SPLIT), OLATDataset(folder, LATTICE_SPLIT, downscale=downscale)


def build_lattice(folder: Path, data: Path, split: str, observations: Sequence[int], *, rig_file: str | None,
                  views: int, lights: int, max_view_angle_deg: float = 0.0, downscale: float = 1.0,
                  framing: str = "real") -> tuple[LatticeSource, OLATDataset]:
    """Write the generation lattice of capture ``data`` [``split``] into ``folder`` (from ``rig_file``, or
    ``views`` cameras and ``lights`` lights sampled: :func:`sampled_rig`, the cameras framed by ``framing``) and read
    it back at ``downscale``."""
    capture = OLATDataset(data, split)
    if rig_file is not None:
        path = Path(rig_file)
        cameras, new_lights = rig_from_file(path, capture)
        source = f"rig {path}"
    else:
        cameras, new_lights = sampled_rig(capture, views, lights, max_view_angle_deg, framing, observations)
        source = f"cameras and lights sampled around {capture.json_path}"
    check_cameras(cameras, capture, source)
    json_path = write_lattice(folder, capture, observations, cameras, new_lights)
    lattice = OLATDataset(folder, LATTICE_SPLIT, downscale=downscale)
    if (lattice.num_views, lattice.num_lights) != (capture.num_views + len(cameras),
                                                   capture.num_lights + len(new_lights)):
        raise DataError(f"{json_path}: {lattice.num_views} views x {lattice.num_lights} lights, expected the "
                        f"capture's {capture.num_views} x {capture.num_lights} plus {len(cameras)} new cameras and "
                        f"{len(new_lights)} new lights ({source}: some coincide)")
    framed = ", framed as the priors'" if framing == "prior" and rig_file is None and cameras else ""
    logger.info("generation lattice %s: %d new cameras%s, %d new lights (%s)", json_path, len(cameras), framed,
                len(new_lights), source)
    return LatticeSource(Path(folder), LATTICE_SPLIT, tuple(range(capture.num_views, lattice.num_views)),
                         tuple(range(capture.num_lights, lattice.num_lights))), lattice
