"""Relighting inference: cache hits and misses, batching independence, manifest, clear errors."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from capture_edits import copy_with_mask_files
from test_relight_model import tiny_model

from diamond_sss.cli.main import main
from diamond_sss.cli.relight_commands import relight
from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.geometry import StoredMapsGeometry
from diamond_sss.diffusion.geometry.base import GeometryError
from diamond_sss.diffusion.relight.inference import load_model, relight_view


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("relight")
    model = tiny_model().eval()
    model.save(root / "model")
    dataset = OLATDataset(embedded_dataset("finetune/torus_jade"))
    view = next(v for v in range(dataset.num_views) if int(dataset.presence[v].sum()) >= 4)
    lights = [int(i) for i in torch.nonzero(dataset.presence[view])[:, 0]]
    return root, model, dataset, view, lights


def test_cache_misses_then_hits(setup, tmp_path):
    _, model, dataset, view, lights = setup
    cache = OutputCache(tmp_path / "cache")
    first = relight_view(
        model, dataset, view, lights[0], lights[1:3], StoredMapsGeometry(), cache, num_steps=2
    )
    assert [r.cached for r in first] == [False, False]
    again = relight_view(
        model, dataset, view, lights[0], lights[1:3], StoredMapsGeometry(), cache, num_steps=2
    )
    assert [r.cached for r in again] == [True, True]
    assert all(torch.equal(a.rgb, b.rgb) for a, b in zip(first, again))
    # A single light, generated alone, equals its batched result up to rounding (per-light noise).
    alone = relight_view(
        model, dataset, view, lights[0], [lights[2]], StoredMapsGeometry(), cache, num_steps=2, seed=0
    )
    assert alone[0].cached
    fresh = relight_view(
        model,
        dataset,
        view,
        lights[0],
        [lights[2]],
        StoredMapsGeometry(),
        OutputCache(tmp_path / "other"),
        num_steps=2,
    )
    assert float((fresh[0].rgb - first[1].rgb).abs().max()) < 0.01
    # Another seed, step count or model is a miss.
    assert not relight_view(
        model, dataset, view, lights[0], [lights[1]], StoredMapsGeometry(), cache, num_steps=2, seed=1
    )[0].cached
    assert not relight_view(
        model, dataset, view, lights[0], [lights[1]], StoredMapsGeometry(), cache, num_steps=3
    )[0].cached
    assert not relight_view(
        tiny_model(seed=9).eval(),
        dataset,
        view,
        lights[0],
        [lights[1]],
        StoredMapsGeometry(),
        cache,
        num_steps=2,
    )[0].cached
    assert not list(cache.root.rglob("*.tmp"))
    mask = first[0].mask[..., 0] > 1e-3
    assert float(first[0].rgb[~mask].abs().max()) == 0.0


def test_relight_command_writes_manifest(setup, tmp_path):
    root, _, dataset, view, lights = setup
    targets = ",".join(str(light) for light in lights[1:3])
    relight(
        dataset.root,
        view,
        lights[0],
        targets,
        "maps",
        tmp_path / "out",
        model=root / "model",
        steps=2,
        cache=tmp_path / "cache",
    )
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert [(m["view"], m["light"]) for m in manifest] == [(view, light) for light in lights[1:3]]
    for item in manifest:
        assert (tmp_path / "out" / item["image"]).is_file() and (tmp_path / "out" / item["mask"]).is_file()
        assert not item["image"].startswith("/")


def test_clear_errors(setup, tmp_path):
    root, model, dataset, view, lights = setup
    cache = OutputCache(tmp_path / "cache")
    missing_light = next(light for light in range(dataset.num_lights) if light not in lights)
    with pytest.raises(ValueError, match=f"no source image of view {view} under light {missing_light}"):
        relight_view(
            model, dataset, view, missing_light, lights[:1], StoredMapsGeometry(), cache, num_steps=1
        )
    with pytest.raises(ValueError, match="light 999 out of range"):
        relight_view(model, dataset, view, lights[0], [999], StoredMapsGeometry(), cache, num_steps=1)
    with pytest.raises(FileNotFoundError, match="relighting model not found"):
        load_model(tmp_path / "nothing")
    with pytest.raises(GeometryError, match="not usable"):
        relight(
            dataset.root,
            view,
            lights[0],
            "1",
            str(tmp_path / "no_run"),
            tmp_path / "out",
            model=root / "model",
        )
    with pytest.raises(ValueError, match="comma-separated"):
        relight(dataset.root, view, lights[0], "a,b", "maps", tmp_path / "out", model=root / "model")


def test_command_line_reports_an_unusable_geometry_source(setup, tmp_path, capsys):
    root, _, dataset, view, lights = setup
    args = ["relight", "--data", str(dataset.root), "--view", str(view), "--source-light", str(lights[0]),
            "--target-lights", "1", "--geometry", str(tmp_path / "no_run"), "--out", str(tmp_path / "out"),
            "--model", str(root / "model")]
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith("diamond-sss: error:") and "not usable" in error and "Traceback" not in error


def test_ensemble_averages_out_the_sampling_noise(setup, tmp_path):
    _, model, dataset, view, lights = setup

    def relit(samples: int, seed: int) -> torch.Tensor:
        cache = OutputCache(tmp_path / f"s{samples}_{seed}")
        return relight_view(
            model, dataset, view, lights[0], [lights[1]], StoredMapsGeometry(), cache, 2, seed, samples
        )[0].rgb

    spread_single = (relit(1, 0) - relit(1, 1)).abs().mean()
    spread_ensemble = (relit(6, 0) - relit(6, 1)).abs().mean()
    assert float(spread_ensemble) < 0.7 * float(spread_single)
    with pytest.raises(ValueError, match="samples must be >= 1"):
        relit(0, 0)


def test_the_source_mask_file_and_the_stored_maps_are_part_of_the_cache_key(setup, tmp_path):
    _, model, dataset, view, lights = setup
    data = copy_with_mask_files(dataset.root, tmp_path / "data")
    cache = OutputCache(tmp_path / "cache")

    def cached() -> bool:
        return relight_view(model, OLATDataset(data), view, lights[0], [lights[1]], StoredMapsGeometry(), cache,
                            num_steps=1, samples=1)[0].cached

    assert not cached() and cached()
    source = OLATDataset(data)
    mask = source.observations[source.observation_index(view, lights[0])].mask_path
    eroded = iio.imread(mask)
    eroded[: eroded.shape[0] // 2] = 0
    iio.imwrite(mask, eroded)
    assert not cached() and cached()  # another source mask: another entry
    depth = data / json.loads((data / "transforms_train.json").read_text())["frames"][view]["depth_path"]
    np.save(depth, np.load(depth) * 1.1)
    assert not cached()  # other stored depth: another entry
