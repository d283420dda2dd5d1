"""The OLAT dataset: a lattice of camera views x point lights, with the observed (view, light) images.

Cameras and lights that repeat across JSON frames are deduplicated into lattice indices (lights within a
tolerance), so capture regimes can select views and lights, and so that a test split's views and lights
are comparable with training ones. Images load lazily into a bounded cache.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from diamond_sss.data.conventions import (
    camera_centers,
    intrinsics_from_fov,
    intrinsics_matrix,
    opengl_c2w_to_opencv_w2c,
    scale_intrinsics,
)
from diamond_sss.data.images import composite_background, load_rgba, resize_area
from diamond_sss.data.transforms import (
    DeclaredCamera,
    ImageRecord,
    ParsedTransforms,
    parse_transforms,
    transforms_path,
)
from diamond_sss.errors import DataError, data_error
from diamond_sss.utils.io import sha256_file, sha256_json
from diamond_sss.utils.logs import warn_once

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: world-to-camera ``w2c [4,4]`` (OpenCV axes), ``K [3,3]`` in pixels, image size."""

    w2c: Tensor
    K: Tensor
    width: int
    height: int
    frame: int

    @property
    def center(self) -> Tensor:
        """World-space camera centre ``[3]``."""
        return camera_centers(self.w2c)

    def resized(self, scale: float) -> Camera:
        """The camera of its image resized by ``scale`` (sides rounded, at least 1 pixel; intrinsics scaled by the
        sides' actual ratios, :func:`~diamond_sss.data.conventions.scale_intrinsics`)."""
        if scale == 1.0:
            return self
        width, height = max(1, round(self.width * scale)), max(1, round(self.height * scale))
        K = scale_intrinsics(self.K, width / self.width, height / self.height)
        return Camera(self.w2c, K, width, height, self.frame)


@dataclass(frozen=True)
class Light:
    """A point light: world position ``[3]`` and RGB intensity ``[3]``."""

    position: Tensor
    intensity: Tensor


@dataclass(frozen=True)
class Observation:
    """One captured image: lattice view and light indices, its file, and the JSON frame it came from."""

    view: int
    light: int
    image_path: Path
    mask_path: Path | None
    frame: int


@dataclass
class ImageSample:
    """A decoded observation: linear premultiplied RGB ``[H,W,3]`` and mask ``[H,W,1]``."""

    index: int
    view: int
    light: int
    rgb: Tensor
    mask: Tensor


@dataclass(frozen=True)
class SceneBounds:
    """Bounding sphere of the object (world units) and the near / far camera depths that enclose it."""

    center: Tensor
    radius: float
    near: float
    far: float


@dataclass
class _ImageCache:
    capacity: int
    entries: OrderedDict = field(default_factory=OrderedDict)

    def get(self, key: int) -> tuple[Tensor, Tensor] | None:
        if key in self.entries:
            self.entries.move_to_end(key)
            return self.entries[key]
        return None

    def put(self, key: int, value: tuple[Tensor, Tensor]) -> None:
        if self.capacity <= 0:
            return
        self.entries[key] = value
        self.entries.move_to_end(key)
        while len(self.entries) > self.capacity:
            self.entries.popitem(last=False)


class OLATDataset:
    """Multi-view OLAT capture read from ``<root>/transforms_<split>.json``.

    Args:
        root: data folder.
        split: selects ``transforms_<split>.json`` (``train``, ``test`` or any other such file).
        downscale: image size divided by this factor (area averaging; intrinsics scaled to match).
        background: ``"black"`` (premultiplied, default) or ``"white"``.
        cache_images: how many decoded images to keep in memory (least recently used are dropped).
        light_tolerance: lights closer than this fraction of the light-rig radius are one lattice light.
    """

    def __init__(self, root: str | Path, split: str = "train", *, downscale: float = 1.0,
                 background: str = "black", cache_images: int = 1024, light_tolerance: float = 1e-3) -> None:
        if downscale < 1.0:
            raise ValueError(f"downscale must be >= 1, got {downscale}")
        if background not in ("black", "white"):
            raise ValueError(f"background must be 'black' or 'white', got {background!r}")
        self.root = Path(root).resolve()
        self.split = split
        self.downscale = float(downscale)
        self.background = background
        self.json_path = transforms_path(self.root, split)
        parsed = parse_transforms(self.json_path)
        records = parsed.records
        self.excluded = parsed.excluded
        self.premultiplied_alpha = parsed.premultiplied_alpha
        self.cameras, view_of_record = _deduplicate_cameras(parsed, self.downscale)
        self.lights, light_of_record = _deduplicate_lights(parsed, light_tolerance)
        self.observations = _observations(self.json_path, records, view_of_record, light_of_record)
        self._geometry_maps = {view_of_record[i]: (r.depth_path, r.normal_path) for i, r in enumerate(records)}
        self._cache = _ImageCache(cache_images)

    # ------------------------------------------------------------------ lattice
    @property
    def num_views(self) -> int:
        return len(self.cameras)

    @property
    def num_lights(self) -> int:
        return len(self.lights)

    def __len__(self) -> int:
        return len(self.observations)

    @property
    def width(self) -> int:
        return self.cameras[0].width

    @property
    def height(self) -> int:
        return self.cameras[0].height

    @cached_property
    def viewmats(self) -> Tensor:
        """World-to-camera matrices of all lattice views, ``[V,4,4]`` OpenCV."""
        return torch.stack([c.w2c for c in self.cameras])

    @cached_property
    def intrinsics(self) -> Tensor:
        """Intrinsics of all lattice views, ``[V,3,3]``."""
        return torch.stack([c.K for c in self.cameras])

    @cached_property
    def camera_centers(self) -> Tensor:
        """Camera centres ``[V,3]``."""
        return camera_centers(self.viewmats)

    @cached_property
    def light_positions(self) -> Tensor:
        """Light positions ``[L,3]``."""
        return torch.stack([light.position for light in self.lights])

    @cached_property
    def light_intensities(self) -> Tensor:
        """Light RGB intensities ``[L,3]``."""
        return torch.stack([light.intensity for light in self.lights])

    @cached_property
    def presence(self) -> Tensor:
        """``[V,L]`` bool: which (view, light) images exist."""
        grid = torch.zeros(self.num_views, self.num_lights, dtype=torch.bool)
        for obs in self.observations:
            grid[obs.view, obs.light] = True
        return grid

    def first_light(self, view: int | None = None) -> Light:
        """The light of the first image (in the data's order) of lattice view ``view``; of the data's first image
        when ``view`` is ``None`` or has no image."""
        first = next((obs for obs in self.observations if obs.view == view), self.observations[0])
        return self.lights[first.light]

    def observation_index(self, view: int, light: int) -> int:
        """Index of the observation of ``(view, light)``; ``KeyError`` when it was not captured."""
        for index, obs in enumerate(self.observations):
            if obs.view == view and obs.light == light:
                return index
        raise KeyError(f"no image of view {view} under light {light} in {self.json_path}")

    @cached_property
    def bounds(self) -> SceneBounds:
        """Bounding sphere and near/far, computed once from the cameras (see :func:`scene_bounds`)."""
        return scene_bounds(self.viewmats, self.intrinsics, torch.tensor([c.width for c in self.cameras]),
                            torch.tensor([c.height for c in self.cameras]))

    # ------------------------------------------------------------------ images
    def load(self, index: int) -> ImageSample:
        """Decode observation ``index`` (cached): linear RGB over the chosen background and its mask."""
        if not 0 <= index < len(self.observations):
            raise IndexError(f"observation {index} out of range (0..{len(self.observations) - 1})")
        obs = self.observations[index]
        cached = self._cache.get(index)
        if cached is None:
            rgb, mask = load_rgba(obs.image_path, obs.mask_path, self.premultiplied_alpha)
            camera = self.cameras[obs.view]
            rgb = resize_area(rgb, camera.height, camera.width)
            mask = resize_area(mask, camera.height, camera.width)
            if float(mask.max()) < 0.5 / 255.0:
                warn_once(logger, "empty-mask", "%s: the mask is empty (frame %d of %s); further empty masks "
                          "are logged at debug level only", obs.image_path, obs.frame, self.json_path)
            cached = (rgb, mask)
            self._cache.put(index, cached)
        rgb, mask = cached
        return ImageSample(index=index, view=obs.view, light=obs.light,
                           rgb=composite_background(rgb, mask, self.background), mask=mask)

    def __getitem__(self, index: int) -> ImageSample:
        return self.load(index)

    def load_batch(self, indices: Sequence[int]) -> tuple[Tensor, Tensor]:
        """Stacked RGB ``[B,H,W,3]`` and masks ``[B,H,W,1]`` of several observations."""
        samples = [self.load(int(i)) for i in indices]
        return torch.stack([s.rgb for s in samples]), torch.stack([s.mask for s in samples])

    def has_geometry_maps(self, view: int) -> bool:
        """Whether depth and normal maps are stored for ``view``."""
        depth, normal = self._geometry_maps.get(view, (None, None))
        return depth is not None and normal is not None

    def load_geometry_maps(self, view: int) -> tuple[Tensor, Tensor]:
        """Stored depth ``[H,W,1]`` (camera z, 0 = background) and world normals ``[H,W,3]`` of ``view``."""
        depth_path, normal_path = self._geometry_maps.get(view, (None, None))
        if depth_path is None or normal_path is None:
            raise DataError(f"{self.json_path}: view {view} has no 'depth_path'/'normal_path' maps")
        camera = self.cameras[view]
        maps = []
        for path, channels in ((depth_path, 1), (normal_path, 3)):
            array = np.load(path, allow_pickle=False).astype(np.float32)
            array = array.reshape(array.shape[0], array.shape[1], channels)
            tensor = torch.from_numpy(array).permute(2, 0, 1)[None]
            tensor = F.interpolate(tensor, size=(camera.height, camera.width), mode="nearest")
            maps.append(tensor[0].permute(1, 2, 0).contiguous())
        return maps[0], maps[1]

    # ------------------------------------------------------------------ selection and batches
    def subset(self, observation_indices: Sequence[int]) -> OLATDataset:
        """A dataset with the same lattice (cameras, lights, indices) restricted to some observations."""
        clone = object.__new__(OLATDataset)
        clone.__dict__.update({k: v for k, v in self.__dict__.items() if k not in _CACHED_PROPERTIES})
        clone.observations = [self.observations[int(i)] for i in observation_indices]
        clone._cache = _ImageCache(self._cache.capacity)
        return clone

    def content_hash(self, observation_indices: Sequence[int]) -> str:
        """SHA-256 of this split's transforms file and of the image (and mask) files of ``observation_indices``:
        what a reconstruction trained on them saw, wherever the capture folder lies."""
        files = [[sha256_file(obs.image_path), sha256_file(obs.mask_path) if obs.mask_path else None]
                 for obs in (self.observations[int(i)] for i in observation_indices)]
        return sha256_json({"transforms": sha256_file(self.json_path), "images": files})

    def batch_indices(self, step: int, batch_size: int, seed: int) -> list[int]:
        """Observation indices of training step ``step``: seeded epochs of random permutations.

        A pure function of ``(step, batch_size, seed)``, so a resumed run draws the same batches.
        """
        if not self.observations:
            raise DataError(f"{self.json_path}: no observations to draw batches from")
        return seeded_epoch_indices(step, batch_size, len(self.observations), seed)

    def iter_batches(self, batch_size: int, seed: int, start_step: int = 0) -> Iterator[list[int]]:
        """Endless iterator of :meth:`batch_indices` from ``start_step`` on."""
        step = start_step
        while True:
            yield self.batch_indices(step, batch_size, seed)
            step += 1

    def summary(self) -> dict:
        """Counts and sizes for ``diamond-sss info``."""
        bounds = self.bounds
        used_views = sorted({o.view for o in self.observations})
        used_lights = sorted({o.light for o in self.observations})
        return {
            "root": str(self.root),
            "split": self.split,
            "views": len(used_views),
            "lights": len(used_lights),
            "lattice_views": self.num_views,
            "lattice_lights": self.num_lights,
            "images": len(self.observations),
            "excluded_images": len(self.excluded),
            "width": self.width,
            "height": self.height,
            "downscale": self.downscale,
            "bounds": {"center": [_rounded(x) for x in bounds.center], "radius": _rounded(bounds.radius),
                       "near": _rounded(bounds.near), "far": _rounded(bounds.far)},
            "geometry_maps": sum(self.has_geometry_maps(v) for v in range(self.num_views)),
        }


def _rounded(value) -> float:
    """``value`` to 6 decimals, with no negative zero."""
    return round(float(value), 6) + 0.0


_CACHED_PROPERTIES = {"presence"}


def seeded_epoch_indices(step: int, batch_size: int, count: int, seed: int) -> list[int]:
    """Indices in ``[0, count)`` of batch ``step``: consecutive slices of seeded per-epoch permutations.

    Every index appears once per epoch; a pure function of its arguments (resumable).
    """
    out = []
    for k in range(batch_size):
        epoch, position = divmod(step * batch_size + k, count)
        out.append(_epoch_permutation(seed, epoch, count)[position])
    return out


@lru_cache(maxsize=4)
def _epoch_permutation(seed: int, epoch: int, count: int) -> tuple[int, ...]:
    """The seeded order of epoch ``epoch`` (drawn once per epoch, not once per step)."""
    generator = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return tuple(torch.randperm(count, generator=generator).tolist())


def scene_bounds(viewmats: Tensor, Ks: Tensor, width: int | Tensor, height: int | Tensor) -> SceneBounds:
    """Bounding sphere of what every camera sees, from the cameras alone (image size in pixels, or per camera ``[V]``).

    Centre: the least-squares point nearest to all optical axes, ``argmin_x sum_v ||(I - d_v d_v^T)(x - c_v)||^2``.
    Radius: the largest sphere at that centre inside every camera's field of view,
    ``min_v |x - c_v| sin(theta_v)`` with ``theta_v`` the smallest half-angle of view ``v`` (objects are framed
    by the cameras, so this bounds them). ``near = max(1e-3, min_v d_v - r)``, ``far = max_v d_v + r``.
    """
    centers = camera_centers(viewmats.double())
    forward = viewmats.double()[:, 2, :3]
    projector = torch.eye(3, dtype=torch.float64) - forward[:, :, None] * forward[:, None, :]
    system = projector.sum(0)
    rhs = (projector @ centers[:, :, None]).sum(0)[:, 0]
    if torch.linalg.eigvalsh(system).min() < 1e-3 * len(centers):
        center = torch.zeros(3, dtype=torch.float64)
    else:
        center = torch.linalg.solve(system, rhs)
    distances = (centers - center).norm(dim=-1)
    fx, fy, cx, cy = Ks[:, 0, 0].double(), Ks[:, 1, 1].double(), Ks[:, 0, 2].double(), Ks[:, 1, 2].double()
    half_u = torch.minimum(cx, width - cx) / fx
    half_v = torch.minimum(cy, height - cy) / fy
    half_angle = torch.atan(torch.minimum(half_u, half_v))
    radius = float((distances * torch.sin(half_angle)).min())
    near = max(1e-3, float(distances.min()) - radius)
    far = float(distances.max()) + radius
    return SceneBounds(center=center.float(), radius=radius, near=near, far=far)


def _camera_matrix(record: ImageRecord | DeclaredCamera, width: int, height: int, size: tuple[int, int],
                   downscale: float) -> tuple[Tensor, Tensor, int, int]:
    """Camera of intrinsics given in pixels of ``width x height``, for images of ``size`` over ``downscale``
    (e.g. a 256 px image of a frame whose intrinsics are stated for 800 px)."""
    intr = record.intrinsics
    if intr.fx is not None:
        cx = intr.cx if intr.cx is not None else 0.5 * width
        cy = intr.cy if intr.cy is not None else 0.5 * height
        K = intrinsics_matrix(intr.fx, intr.fy, cx, cy)
    else:
        K = intrinsics_from_fov(intr.fov_x, width, height, intr.fov_y)
    new_width = max(1, round(size[0] / downscale))
    new_height = max(1, round(size[1] / downscale))
    if (new_width, new_height) != (width, height):
        K = scale_intrinsics(K, new_width / width, new_height / height)
    w2c = opengl_c2w_to_opencv_w2c(torch.from_numpy(record.c2w)).float()
    return w2c, K, new_width, new_height


def _deduplicate_cameras(parsed: ParsedTransforms, downscale: float) -> tuple[list[Camera], list[int]]:
    """Declared cameras first (``frame = -1``), then each new camera of the images; image -> view index."""
    cameras: list[Camera] = []
    keys: dict[tuple, int] = {}
    records = parsed.records
    declared = [(cam.width or records[0].width, cam.height or records[0].height) for cam in parsed.cameras]
    entries: list[tuple[ImageRecord | DeclaredCamera, int, int, tuple[int, int], int]] = [
        (cam, *size, size, -1) for cam, size in zip(parsed.cameras, declared)
    ] + [(record, record.width, record.height, record.file_size, record.frame) for record in records]
    view_of_entry = []
    for entry, width, height, size, frame in entries:
        key = (tuple(np.round(entry.c2w, 6).ravel().tolist()), entry.intrinsics)
        if key not in keys:
            w2c, K, new_width, new_height = _camera_matrix(entry, width, height, size, downscale)
            keys[key] = len(cameras)
            cameras.append(Camera(w2c=w2c, K=K, width=new_width, height=new_height, frame=frame))
        view_of_entry.append(keys[key])
    return cameras, view_of_entry[len(parsed.cameras):]


def _deduplicate_lights(parsed: ParsedTransforms, tolerance: float) -> tuple[list[Light], list[int]]:
    """Declared lights first, then each new light of the images (within ``tolerance`` of the rig radius)."""
    entries = [(light.position, light.intensity) for light in parsed.lights] + [
        (r.light_position, r.light_intensity) for r in parsed.records]
    positions = np.stack([position for position, _ in entries])
    scale = max(float(np.linalg.norm(positions, axis=-1).max()), 1e-6)
    unique_pos: list[np.ndarray] = []
    unique_rgb: list[np.ndarray] = []
    light_of_entry = []
    for position, intensity in entries:
        match = -1
        if unique_pos:
            dist = np.linalg.norm(np.stack(unique_pos) - position, axis=-1)
            for candidate in np.flatnonzero(dist <= tolerance * scale):
                if np.allclose(unique_rgb[candidate], intensity, rtol=1e-3, atol=1e-6):
                    match = int(candidate)
                    break
        if match < 0:
            match = len(unique_pos)
            unique_pos.append(position)
            unique_rgb.append(intensity)
        light_of_entry.append(match)
    light_of_record = light_of_entry[len(parsed.lights):]
    lights = [Light(position=torch.tensor(p, dtype=torch.float32), intensity=torch.tensor(c, dtype=torch.float32))
              for p, c in zip(unique_pos, unique_rgb)]
    return lights, light_of_record


def _observations(json_path: Path, records: list[ImageRecord], view_of_record: list[int],
                  light_of_record: list[int]) -> list[Observation]:
    observations = []
    seen: dict[tuple[int, int], Path] = {}
    first_size: dict[int, tuple[int, int]] = {}
    for record, view, light in zip(records, view_of_record, light_of_record):
        reference = first_size.setdefault(view, record.file_size)
        if record.file_size != reference:
            file_w, file_h = record.file_size
            raise data_error(json_path, f"image {record.image_path} is {file_w}x{file_h} but view {view} is "
                             f"{reference[0]}x{reference[1]}", frame=record.frame, key="w/h")
        if (view, light) in seen:
            logger.warning("%s: frame %d: %s repeats view %d under light %d (already %s); keeping the first",
                           json_path, record.frame, record.image_path, view, light, seen[(view, light)])
            continue
        seen[(view, light)] = record.image_path
        observations.append(Observation(view=view, light=light, image_path=record.image_path,
                                        mask_path=record.mask_path, frame=record.frame))
    return observations


def directions_from(points: Tensor, center: Tensor) -> Tensor:
    """Unit directions from ``center [3]`` to ``points [N,3]``."""
    offset = points - center
    return offset / offset.norm(dim=-1, keepdim=True).clamp_min(1e-12)
