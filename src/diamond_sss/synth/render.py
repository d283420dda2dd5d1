"""Physically based OLAT rendering with Mitsuba 3 and the synthetic-capture pipeline.

One Mitsuba scene per object: the closed mesh with a ``homogeneous`` interior medium behind its boundary
BSDF, one point light and a pinhole camera (``hdrfilm`` RGBA, box filter), rendered with ``volpath``.
The light position and camera pose are updated in place between images. Point-light radiant intensity is
``pi r_l^2`` per channel, so the irradiance at the origin is ``pi`` (a white Lambertian facing the light
would have radiance 1). Coverage (the PNG alpha), depth (camera-space z) and world normals come from an
``aov`` pass per view whose values are coverage-weighted at silhouettes and are divided by its alpha.
The coverage replaces ``volpath``'s alpha, which misses rays that cross a thin null-bounded medium
without scattering. The radiance is premultiplied by construction (the background contributes 0).

Exposure: one scalar per object, ``target / p99`` where ``p99`` is the largest 99th percentile of
foreground linear RGB values over a few front-lit probe renders of training views; fixed for all images.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from diamond_sss.data.conventions import opengl_c2w_to_opencv_w2c
from diamond_sss.data.errors import DataError
from diamond_sss.synth.materials import TranslucentMaterial, get_material
from diamond_sss.synth.scene import (
    LightStage,
    LightStageConfig,
    build_light_stage,
    interleaved_test_indices,
    view_light_subsets,
)
from diamond_sss.synth.shapes import TriangleMesh, build_shape
from diamond_sss.synth.writer import (
    FrameRecord,
    encode_rgba8,
    write_json,
    write_npy,
    write_png,
    write_transforms,
)

logger = logging.getLogger(__name__)

PREFERRED_VARIANT = "llvm_ad_rgb"
FALLBACK_VARIANT = "scalar_rgb"
# Mitsuba looks down +Z with +X to the left; OpenGL looks down -Z with +X to the right: flip X and Z.
_GL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])


@functools.lru_cache(maxsize=1)
def select_variant() -> str:
    """Activate ``llvm_ad_rgb`` if it works here (needs libLLVM 19), else ``scalar_rgb`` (logged once).

    Returns the variant's name. Cached: the choice is made once per process.
    """
    import mitsuba as mi

    try:
        mi.set_variant(PREFERRED_VARIANT)
        mi.load_dict({"type": "sphere"})
        return PREFERRED_VARIANT
    except Exception as err:  # noqa: BLE001 - any failure of the JIT backend means: use the scalar variant
        logger.warning(
            "Mitsuba %s unavailable (%s); falling back to %s", PREFERRED_VARIANT, err, FALLBACK_VARIANT
        )
        mi.set_variant(FALLBACK_VARIANT)
        return FALLBACK_VARIANT


def mitsuba_to_world(c2w_opengl: np.ndarray) -> np.ndarray:
    """Mitsuba sensor ``to_world`` of an OpenGL camera-to-world matrix: ``c2w diag(-1, 1, -1, 1)``."""
    return np.asarray(c2w_opengl, dtype=np.float64) @ _GL_TO_MITSUBA


def opencv_w2c(c2w_opengl: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera ``[4,4]`` (float64) of an OpenGL camera-to-world matrix."""
    return opengl_c2w_to_opencv_w2c(torch.from_numpy(np.asarray(c2w_opengl, dtype=np.float64))).numpy()


def image_seed(object_seed: int, split: str, view: int, light: int, noise_seed: int = 0) -> int:
    """Mitsuba sampler seed (uint32) of image ``(view, light)`` of ``split``, derived from the object seed.

    A non-zero ``noise_seed`` gives the same image with independent Monte Carlo noise.
    """
    split_id = {"train": 0, "test": 1, "probe": 2, "geometry": 3, "novel_view": 4, "novel_light": 5}[split]
    sequence = np.random.SeedSequence([object_seed, split_id, view, light] + ([noise_seed] if noise_seed else []))
    return int(sequence.generate_state(1, dtype=np.uint32)[0])


@dataclass(frozen=True)
class RenderSettings:
    """Film and integrator settings. ``fov_x`` in radians."""

    width: int = 64
    height: int = 64
    spp: int = 64
    fov_x: float = math.radians(32.0)
    max_depth: int = 64
    geometry_spp: int = 64
    light_radius: float = 5.0

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1 or self.spp < 1 or self.geometry_spp < 1:
            raise ValueError(f"width, height, spp and geometry_spp must be positive: {self}")
        if not 0.0 < self.fov_x < math.pi:
            raise ValueError(f"fov_x must be in (0, pi) radians, got {self.fov_x}")


class OlatRenderer:
    """Renders one translucent object under one point light at a time, from any camera.

    ``render`` returns linear premultiplied RGBA ``[H,W,4]`` float32 (unexposed); ``render_geometry``
    returns ``(alpha [H,W], depth [H,W], normals [H,W,3])``, zero outside the object.
    """

    def __init__(self, mesh: TriangleMesh, material: TranslucentMaterial, settings: RenderSettings):
        import mitsuba as mi

        self.variant = select_variant()
        self.settings = settings
        self.light_intensity = math.pi * settings.light_radius**2
        with tempfile.TemporaryDirectory() as tmp:
            ply_path = Path(tmp) / "object.ply"
            _mitsuba_mesh(mesh).write_ply(str(ply_path))
            self.scene = mi.load_dict(
                {
                    "type": "scene",
                    "object": {
                        "type": "ply",
                        "filename": str(ply_path),
                        "face_normals": False,
                        "bsdf": material.bsdf_dict(),
                        "interior": material.medium_dict(),
                    },
                    "light": {
                        "type": "point",
                        "position": [0.0, 0.0, settings.light_radius],
                        "intensity": {"type": "rgb", "value": [self.light_intensity] * 3},
                    },
                    "sensor": {
                        "type": "perspective",
                        "fov": math.degrees(settings.fov_x),
                        "fov_axis": "x",
                        "near_clip": 0.01,
                        "far_clip": 100.0,
                        "film": {
                            "type": "hdrfilm",
                            "width": settings.width,
                            "height": settings.height,
                            "pixel_format": "rgba",
                            "rfilter": {"type": "box"},
                        },
                        "sampler": {"type": "independent", "sample_count": settings.spp},
                    },
                }
            )
        self.integrator = mi.load_dict({"type": "volpath", "max_depth": settings.max_depth})
        self.aov_integrator = mi.load_dict(
            {"type": "aov", "aovs": "pos:position,nrm:sh_normal", "integrator": {"type": "direct"}}
        )
        self.params = mi.traverse(self.scene)

    def _set_camera(self, c2w: np.ndarray) -> None:
        import mitsuba as mi

        self.params["sensor.to_world"] = mi.ScalarTransform4f(mitsuba_to_world(c2w).tolist())

    def render(
        self, c2w: np.ndarray, light_position: np.ndarray, seed: int, spp: int | None = None
    ) -> np.ndarray:
        """Linear RGBA of the object seen from ``c2w`` (OpenGL) lit by a point light at ``light_position``."""
        import mitsuba as mi

        self._set_camera(c2w)
        self.params["light.position"] = mi.ScalarPoint3f(*map(float, light_position))
        self.params.update()
        image = mi.render(self.scene, integrator=self.integrator, seed=seed, spp=spp or self.settings.spp)
        return np.array(image, dtype=np.float32)

    def render_geometry(self, c2w: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coverage, camera-space depth ``z`` and unit world normals, zero where coverage is 0."""
        import mitsuba as mi

        self._set_camera(c2w)
        self.params.update()
        channels = np.array(
            mi.render(self.scene, integrator=self.aov_integrator, seed=seed, spp=self.settings.geometry_spp),
            dtype=np.float64,
        )
        alpha = channels[..., 3]
        covered = alpha > 1e-6
        safe_alpha = np.where(covered, alpha, 1.0)[..., None]
        position = channels[..., 4:7] / safe_alpha
        w2c = opencv_w2c(c2w)
        depth = np.where(covered, position @ w2c[2, :3] + w2c[2, 3], 0.0)
        normal = channels[..., 7:10]
        norm = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = np.where(covered[..., None] & (norm > 1e-9), normal / np.maximum(norm, 1e-9), 0.0)
        return alpha.astype(np.float32), depth.astype(np.float32), normal.astype(np.float32)


def _mitsuba_mesh(mesh: TriangleMesh):
    """A Mitsuba ``Mesh`` with the given vertices, faces and vertex normals."""
    import drjit as dr
    import mitsuba as mi

    out = mi.Mesh("object", len(mesh.vertices), len(mesh.faces), has_vertex_normals=True)
    params = mi.traverse(out)
    params["vertex_positions"] = dr.ravel(mi.TensorXf(mesh.vertices.astype(np.float32)))
    params["faces"] = dr.ravel(mi.TensorXu(mesh.faces.astype(np.uint32)))
    params["vertex_normals"] = dr.ravel(mi.TensorXf(mesh.normals.astype(np.float32)))
    params.update()
    return out


def compute_exposure(
    renderer: OlatRenderer,
    c2w: np.ndarray,
    lights: np.ndarray,
    object_seed: int,
    probes: int = 4,
    target: float = 0.9,
    percentile: float = 99.0,
) -> float:
    """``target / max_i p_i``, ``p_i`` the ``percentile`` of foreground (alpha > 0.5) linear RGB of probe
    ``i``: ``probes`` evenly spread training views, each lit by the training light closest to its camera."""
    views = np.unique(np.linspace(0, len(c2w) - 1, min(probes, len(c2w))).round().astype(int))
    light_dirs = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    values = []
    for view in views:
        eye = c2w[view, :3, 3]
        light = int(np.argmax(light_dirs @ (eye / np.linalg.norm(eye))))
        image = renderer.render(
            c2w[view],
            lights[light],
            image_seed(object_seed, "probe", int(view), light),
            spp=max(16, renderer.settings.spp // 4),
        )
        foreground = image[..., 3] > 0.5
        if foreground.any():
            values.append(float(np.percentile(image[..., :3][foreground], percentile)))
    if not values or max(values) <= 0.0:
        raise RuntimeError("exposure probes saw no lit object; check the camera and light placement")
    return target / max(values)


def parse_subset(spec: str, views: int, lights: int) -> dict[str, list[tuple[int, int]]]:
    """Training-lattice pairs selected by ``spec``: comma-separated ``kind:VxL`` or ``pair:V/L`` terms.

    ``relight:VxL``: V evenly spread views (indices ``floor((i + 1/2) views / V)``), each under L evenly
    spread lights (fixed view, varying light). ``novelview:VxL``: L lights at ``floor(j lights / L)``, each
    seen from V views at ``floor(i views / V)`` (fixed light, varying view). ``pair:V/L``: the one image of
    view V under light L (0-based lattice indices; repeat the term for more). Returns pairs per kind.
    """
    out: dict[str, list[tuple[int, int]]] = {}
    for term in filter(None, (t.strip() for t in spec.split(","))):
        kind, _, size = term.partition(":")
        if kind == "pair":
            view, _, light = size.partition("/")
            if not (view.isdigit() and light.isdigit()):
                raise ValueError(f"bad subset term {term!r}; expected 'pair:V/L' with lattice indices V and L")
            if not (int(view) < views and int(light) < lights):
                raise ValueError(f"subset term {term!r} needs a view in 0..{views - 1} and a light in 0..{lights - 1}")
            out.setdefault("pair", []).append((int(view), int(light)))
            continue
        n_views, _, n_lights = size.partition("x")
        if kind not in ("relight", "novelview") or not (n_views.isdigit() and n_lights.isdigit()):
            raise ValueError(f"bad subset term {term!r}; expected 'relight:VxL', 'novelview:VxL' or 'pair:V/L'")
        nv, nl = int(n_views), int(n_lights)
        if not (1 <= nv <= views and 1 <= nl <= lights):
            raise ValueError(f"subset term {term!r} needs 1..{views} views and 1..{lights} lights")
        shift = 0.5 if kind == "relight" else 0.0
        view_idx = np.floor((np.arange(nv) + shift) * views / nv).astype(int)
        light_idx = np.floor((np.arange(nl) + shift) * lights / nl).astype(int)
        out[kind] = [(int(v), int(l)) for v in view_idx for l in light_idx]
    if not out:
        raise ValueError(f"empty subset spec {spec!r}")
    return out


SPLIT_RIGS: dict[str, tuple[str, str]] = {
    "train": ("train", "train"),
    "test": ("test", "test"),
    "novel_view": ("test", "train"),
    "novel_light": ("train", "test"),
}
"""Per split, the rig sets its ``(cameras, lights)`` come from. ``novel_view`` (test cameras under training lights)
and ``novel_light`` (training cameras under test lights) split the test split's error into what a novel view and a
novel light cost."""


@dataclass(frozen=True)
class SynthConfig:
    """Everything that defines one synthetic object capture."""

    shape: str
    material: str
    out: Path
    stage: LightStageConfig
    size: int = 64
    spp: int = 64
    maps: bool = True
    subset: str | None = None
    seed: int = 0
    mesh_resolution: int = 64
    noise_seed: int = 0
    train: bool = True
    cross_splits: bool = False


def noise_reference_config(data: Path, out: Path, noise_seed: int = 1, cross_splits: bool = False) -> SynthConfig:
    """The test split of the capture in ``data`` (read from its ``meta.json``) with independent noise, and with
    ``cross_splits`` the ``novel_view`` and ``novel_light`` splits (:data:`SPLIT_RIGS`).

    Same object, rig, exposure and sample count; only the samplers' seeds change. Rendered into ``out``.
    """
    path = Path(data) / "meta.json"
    if not path.is_file():
        raise DataError(f"{path} is missing: only a capture made by `diamond-sss synth` can be rendered again")
    try:
        meta = json.loads(path.read_text())
        stage = dict(meta["stage"])
        stage["camera_band"], stage["light_band"] = tuple(stage["camera_band"]), tuple(stage["light_band"])
        return SynthConfig(shape=meta["shape"]["name"], material=meta["material"]["name"], out=Path(out),
                           stage=LightStageConfig(**stage), size=int(meta["size"][0]), spp=int(meta["spp"]),
                           seed=int(meta["seed"]), mesh_resolution=int(meta["shape"]["mesh_resolution"]),
                           noise_seed=noise_seed, train=False, cross_splits=cross_splits)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: not a `diamond-sss synth` meta file ({type(exc).__name__}: {exc})") from exc


def plan_pairs(config: SynthConfig) -> dict[str, list[tuple[int, int]]]:
    """``(view, light)`` pairs rendered per split: the training lattice (every view under every light, or under its
    ``lights_per_view`` random lights: :func:`view_light_subsets`), or the ``subset`` of it; the full test lattice
    (novel views x novel lights; empty when either count is 0) and, with ``cross_splits``, ``novel_view`` (every
    test view under ``test_lights`` evenly spread training lights) and ``novel_light`` (``test_views`` evenly spread
    training views under every test light).

    A ``subset`` pair that the incomplete lattice did not capture is an error naming it."""
    st = config.stage
    lattice = [(v, l) for v, lights in enumerate(view_light_subsets(st)) for l in lights]
    if not config.train:
        train = []
    elif config.subset:
        selected = parse_subset(config.subset, st.views, st.lights)
        train = sorted({pair for pairs in selected.values() for pair in pairs})
        missing = sorted(set(train) - set(lattice))
        if missing:
            raise ValueError(f"subset {config.subset!r} asks for (view, light) pairs {missing[:5]} "
                             f"({len(missing)} in all) that lights_per_view={st.lights_per_view} leaves uncaptured; "
                             "pick pairs of the incomplete lattice (see meta.json 'pairs')")
    else:
        train = lattice
    test = [(v, l) for v in range(st.test_views) for l in range(st.test_lights)]
    pairs = {"train": train, "test": test}
    if config.cross_splits and test:
        spread_lights = interleaved_test_indices(st.lights, min(st.test_lights, st.lights)).tolist()
        spread_views = interleaved_test_indices(st.views, min(st.test_views, st.views)).tolist()
        pairs["novel_view"] = [(v, l) for v in range(st.test_views) for l in spread_lights]
        pairs["novel_light"] = [(v, l) for v in spread_views for l in range(st.test_lights)]
    return pairs


def synthesize(config: SynthConfig, on_image: Callable[[], None] | None = None) -> dict:
    """Render and write one object (images, maps, ``transforms_*.json``, ``meta.json``); returns the meta."""
    start = time.perf_counter()
    material = get_material(config.material)
    mesh = build_shape(config.shape, seed=config.seed, resolution=config.mesh_resolution)
    stage = build_light_stage(config.stage)
    settings = RenderSettings(
        width=config.size,
        height=config.size,
        spp=config.spp,
        fov_x=stage.fov_x,
        light_radius=config.stage.light_radius,
    )
    renderer = OlatRenderer(mesh, material, settings)
    exposure = compute_exposure(renderer, stage.train_c2w, stage.train_lights, config.seed)
    pairs = plan_pairs(config)
    out = Path(config.out)
    for split in pairs:
        if pairs[split]:
            frames = _render_split(renderer, stage, split, pairs[split], exposure, config, on_image)
            write_transforms(out, split, stage.fov_x, config.size, config.size, frames)
    meta = {
        "shape": {
            "name": config.shape,
            "seed": config.seed,
            "mesh_resolution": config.mesh_resolution,
            "vertices": len(mesh.vertices),
            "faces": len(mesh.faces),
            "radius": 1.0,
        },
        "material": asdict(material),
        "seed": config.seed,
        "noise_seed": config.noise_seed,
        "spp": config.spp,
        "geometry_spp": settings.geometry_spp,
        "max_depth": settings.max_depth,
        "integrator": "volpath",
        "size": [config.size, config.size],
        "camera_angle_x": stage.fov_x,
        "exposure": exposure,
        "exposure_rule": "0.9 / max over 4 front-lit probes of the 99th percentile of foreground linear RGB",
        "light_radiant_intensity": renderer.light_intensity,
        "light_intensities_note": "transforms list [1,1,1]; physical intensity = light_radiant_intensity",
        "stage": asdict(config.stage),
        "cameras": {"train": stage.train_c2w.tolist(), "test": stage.test_c2w.tolist()},
        "lights": {"train": stage.train_lights.tolist(), "test": stage.test_lights.tolist()},
        "lights_per_view": config.stage.lights_per_view,
        "subset": config.subset,
        "subset_pairs": parse_subset(config.subset, config.stage.views, config.stage.lights)
        if config.subset
        else None,
        "pairs": {split: [list(p) for p in split_pairs] for split, split_pairs in pairs.items()},
        "mitsuba_variant": renderer.variant,
        "mitsuba_version": _mitsuba_version(),
        "render_seconds": time.perf_counter() - start,
    }
    write_json(out / "meta.json", meta)
    return meta


def _render_split(
    renderer: OlatRenderer,
    stage: LightStage,
    split: str,
    pairs: list[tuple[int, int]],
    exposure: float,
    config: SynthConfig,
    on_image: Callable[[], None] | None,
) -> list[FrameRecord]:
    camera_set, light_set = SPLIT_RIGS[split]
    c2ws = stage.train_c2w if camera_set == "train" else stage.test_c2w
    lights = stage.train_lights if light_set == "train" else stage.test_lights
    out = Path(config.out)
    frames = []
    for view in sorted({v for v, _ in pairs}):
        frame = FrameRecord(c2w=c2ws[view])
        coverage, depth, normal = renderer.render_geometry(
            c2ws[view], image_seed(config.seed, "geometry", view, 0)
        )
        if config.maps:
            frame.depth_path = f"{split}/v{view:03d}_depth.npy"
            frame.normal_path = f"{split}/v{view:03d}_normal.npy"
            write_npy(out / frame.depth_path, depth)
            write_npy(out / frame.normal_path, normal)
        for light in sorted(l for v, l in pairs if v == view):
            seed = image_seed(config.seed, split, view, light, config.noise_seed)
            image = renderer.render(c2ws[view], lights[light], seed)
            image[..., 3] = coverage
            rel = f"{split}/v{view:03d}_l{light:03d}.png"
            write_png(out / rel, encode_rgba8(image, exposure))
            frame.file_paths.append(rel)
            frame.light_positions.append(lights[light].tolist())
            frame.light_intensities.append([1.0, 1.0, 1.0])
            if on_image is not None:
                on_image()
        frames.append(frame)
    return frames


def _mitsuba_version() -> str:
    import mitsuba as mi

    return mi.__version__
