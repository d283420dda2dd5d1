"""``diamond-sss synth``: render a synthetic translucent OLAT capture with Mitsuba 3.

The renderer (torch, Mitsuba) is imported when the command runs, so ``diamond-sss --help`` stays fast.
"""

from __future__ import annotations

import pathlib


def synth(
    shape: str,
    material: str,
    out: pathlib.Path,
    views: int = 40,
    lights: int = 24,
    size: int = 64,
    spp: int = 64,
    test_views: int = 8,
    test_lights: int = 6,
    seed: int = 0,
    maps: bool = True,
    subset: str | None = None,
    camera_radius: float = 4.0,
    light_radius: float = 5.0,
    fov_x_deg: float = 32.0,
    camera_band: tuple[float, float] = (-0.35, 0.85),
    light_band: tuple[float, float] = (-0.5, 0.95),
    lights_per_view: int | None = None,
    noise_seed: int = 0,
    train: bool = True,
    cross_splits: bool = False,
) -> None:
    """Render a physically based OLAT capture of a procedural translucent object (Mitsuba 3, volpath).

    Writes NeRF-synthetic style ``transforms_train.json`` / ``transforms_test.json`` (one frame per view,
    one RGBA PNG per light), per-view depth / normal ``.npy`` maps and ``meta.json`` into ``out``. The test
    split uses novel cameras and novel lights, interleaved between the training ones.

    Args:
        shape: Procedural shape: blob, bunny, bust, knot, sphere or torus.
        material: Translucent material: glazed_wax, jade, marble, skin, soap or wax.
        out: Output folder of the object.
        views: Training camera views on a sphere around the object.
        lights: Training point lights on a larger sphere.
        size: Image width and height in pixels.
        spp: Samples per pixel of each OLAT image.
        test_views: Novel test views (0: no test split).
        test_lights: Novel test lights (0: no test split).
        seed: Object seed (camera/light azimuths, blob shape, per-image sampler seeds).
        maps: Also write per-view depth (camera z) and world-normal maps.
        subset: Render only part of the training lattice, e.g. "relight:3x10,novelview:10x3"
            (3 views x 10 lights each, plus 3 lights x 10 views each), or "pair:3/5,pair:7/2" (single images).
        camera_radius: Distance of the cameras from the object centre (object radius 1).
        light_radius: Distance of the lights from the object centre.
        fov_x_deg: Horizontal field of view in degrees.
        camera_band: Heights z/r the cameras span (-0.5: 30 degrees below the horizon; -1 1: the full sphere).
        light_band: Heights z/r the lights span.
        lights_per_view: Light each training view by a seeded random K of the training lights only (an
            incomplete lattice, recorded in meta.json); default: every light. The test split stays complete.
        noise_seed: Non-zero: the same images with independent Monte Carlo noise (a second render of a
            capture measures its noise ceiling: see benchmarks/quality.py).
        train: Render the training lattice (--no-train: only the test split).
        cross_splits: Also render ``novel_view`` (the test views under evenly spread training lights) and
            ``novel_light`` (evenly spread training views under the test lights): they split the test error into
            what a novel view and a novel light cost (see benchmarks/quality.py --cross-splits).
    """
    from tqdm import tqdm

    from diamond_sss.synth.materials import get_material
    from diamond_sss.synth.render import SynthConfig, plan_pairs, synthesize
    from diamond_sss.synth.scene import LightStageConfig
    from diamond_sss.synth.shapes import shape_names

    if shape not in shape_names():
        raise ValueError(f"unknown shape {shape!r}; valid shapes: {', '.join(shape_names())}")
    get_material(material)
    stage = LightStageConfig(
        views=views,
        lights=lights,
        test_views=test_views,
        test_lights=test_lights,
        camera_radius=camera_radius,
        light_radius=light_radius,
        fov_x_deg=fov_x_deg,
        camera_band=camera_band,
        light_band=light_band,
        seed=seed,
        lights_per_view=lights_per_view,
    )
    config = SynthConfig(
        shape=shape,
        material=material,
        out=pathlib.Path(out),
        stage=stage,
        size=size,
        spp=spp,
        maps=maps,
        subset=subset,
        seed=seed,
        noise_seed=noise_seed,
        train=train,
        cross_splits=cross_splits,
    )
    total = sum(len(p) for p in plan_pairs(config).values())
    with tqdm(total=total, desc=f"synth {shape}/{material}", unit="img") as bar:
        synthesize(config, on_image=bar.update)

