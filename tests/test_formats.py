"""The SSS-3DGS data format exactly: one committed fixture per variant (scripts/make_format_fixtures.py)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import torch
from repo_scripts import load_script

from diamond_sss.data import DataError, OLATDataset
from diamond_sss.data.transforms import is_excluded, read_exclude_list

FORMATS = Path(__file__).parent / "fixtures" / "formats"
SCRIPT = "scripts/make_format_fixtures.py"


def lattice(dataset: OLATDataset) -> list[tuple[int, int]]:
    return [(o.view, o.light) for o in dataset.observations]


def test_the_script_writes_the_committed_fixtures(tmp_path):
    load_script(SCRIPT).make_fixtures(tmp_path)
    written = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    committed = sorted(p.relative_to(FORMATS) for p in FORMATS.rglob("*") if p.is_file())
    assert written == committed
    for relative in written:
        assert (tmp_path / relative).read_bytes() == (FORMATS / relative).read_bytes(), relative


def test_full_size_release_object_with_exclude_list():
    dataset = OLATDataset(FORMATS / "object_full")
    assert dataset.excluded == ("train/r_000_l_001", "train/r_001_l_002")
    assert [o.image_path.name for o in dataset.observations] == [
        "r_000_l_000.png", "r_000_l_002.png", "r_001_l_000.png", "r_001_l_001.png"]
    assert (dataset.num_views, dataset.num_lights, dataset.width, dataset.height) == (2, 3, 8, 8)
    K0, K1 = dataset.cameras[0].K, dataset.cameras[1].K
    assert torch.allclose(K0, torch.tensor([[9.5, 0, 4.0], [0, 9.5, 4.0], [0, 0, 1]]))
    assert torch.allclose(K1, torch.tensor([[10.5, 0, 4.0], [0, 10.5, 4.5], [0, 0, 1]]))
    by_position = {round(float(light.position[1]), 3): light.intensity.float() for light in dataset.lights}
    assert torch.allclose(by_position[round(5 * math.sin(2 * math.pi / 3), 3)], torch.tensor([1.0, 0.95, 0.8]))
    sample = dataset.load(0)
    assert sample.mask[0, 0] == 0 and sample.mask[4, 4] == 1 and float(sample.rgb[4, 4, 0]) > 0
    assert dataset.summary()["excluded_images"] == 2


def test_small_release_object_scales_the_full_size_intrinsics():
    small = OLATDataset(FORMATS / "object_small")
    full = OLATDataset(FORMATS / "split_variants", "train_full", downscale=2.0)
    assert (small.width, small.height, len(small)) == (4, 4, 6) and small.excluded == ()
    for a, b in zip(small.cameras, full.cameras):
        assert (a.width, a.height) == (b.width, b.height) == (4, 4)
        assert torch.allclose(a.K, b.K) and torch.equal(a.w2c, b.w2c)
    assert torch.allclose(small.cameras[1].K, torch.tensor([[5.25, 0, 2.0], [0, 5.25, 2.25], [0, 0, 1]]))


def test_size_variants_as_splits_of_one_object():
    full = OLATDataset(FORMATS / "split_variants", "train_full")
    small = OLATDataset(FORMATS / "split_variants", "train_small")
    assert (full.width, small.width) == (8, 4) and lattice(full) == lattice(small) and len(full) == 6
    with pytest.raises(DataError, match=r"split 'train' not found; splits in .*\['train_full', 'train_small'\]"):
        OLATDataset(FORMATS / "split_variants", "train")


def test_per_image_nrhints_style():
    dataset = OLATDataset(FORMATS / "nrhints")
    assert (dataset.num_views, dataset.num_lights, len(dataset)) == (2, 3, 6)
    assert sorted(lattice(dataset)) == [(v, light) for v in range(2) for light in range(3)]
    focal = 4.0 / math.tan(0.45)
    assert math.isclose(float(dataset.cameras[0].K[0, 0]), focal, rel_tol=1e-6)
    assert all(torch.allclose(light.intensity.float(), torch.full((3,), 2.0)) for light in dataset.lights)


def test_exclude_names_with_or_without_png_paths_or_file_names(tmp_path):
    (tmp_path / "exclude_list.txt").write_text("# broken captures\n r_1.png \n\ntrain/r_2\n.\\test\\r_3.PNG\n")
    names = read_exclude_list(tmp_path)
    assert names == {"r_1", "train/r_2", "test/r_3"}
    assert is_excluded("train/r_1", names) and is_excluded("./train/r_1.png", names)
    assert is_excluded("train/r_2.png", names) and not is_excluded("test/r_2", names)
    assert not is_excluded("train/r_10", names) and read_exclude_list(tmp_path / "none") == frozenset()


def test_every_image_excluded_or_a_bad_width_is_an_error(tmp_path):
    root = tmp_path / "object"
    shutil.copytree(FORMATS / "object_small", root)
    (root / "exclude_list.txt").write_text("\n".join(f"r_{v:03d}_l_{k:03d}" for v in range(2) for k in range(3)))
    with pytest.raises(DataError, match=r"transforms_train\.json: key 'frames': every image is named in .*exclude"):
        OLATDataset(root)
    (root / "exclude_list.txt").unlink()
    payload = json.loads((root / "transforms_train.json").read_text())
    payload["frames"][1]["width"] = "800"
    (root / "transforms_train.json").write_text(json.dumps(payload))
    with pytest.raises(DataError, match=r"frame 1: key 'width': expected a positive whole number of pixels"):
        OLATDataset(root)
