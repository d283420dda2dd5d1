"""`diamond-sss subset`: a regime's images exported as a capture of their own, loaded back unchanged."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from diamond_sss.cli.main import main
from diamond_sss.data import DataError, OLATDataset, select_regime
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.data.export import export_regime

FORMATS = Path(__file__).parent / "fixtures" / "formats"


def _by_file(dataset: OLATDataset) -> dict[str, int]:
    return {obs.image_path.relative_to(dataset.root).as_posix(): i for i, obs in enumerate(dataset.observations)}


def _assert_same_images(source: OLATDataset, exported: OLATDataset, files: list[str]) -> None:
    """The exported images of ``files`` have the source's pixels, masks, cameras, lights and geometry maps."""
    src_index, out_index = _by_file(source), _by_file(exported)
    assert sorted(out_index) == sorted(files)
    for name in files:
        a, b = source.load(src_index[name]), exported.load(out_index[name])
        torch.testing.assert_close(b.rgb, a.rgb, rtol=0, atol=0)
        torch.testing.assert_close(b.mask, a.mask, rtol=0, atol=0)
        cam_a, cam_b = source.cameras[a.view], exported.cameras[b.view]
        torch.testing.assert_close(cam_b.w2c, cam_a.w2c, rtol=0, atol=0)
        torch.testing.assert_close(cam_b.K, cam_a.K, rtol=0, atol=0)
        light_a, light_b = source.lights[a.light], exported.lights[b.light]
        torch.testing.assert_close(light_b.position, light_a.position, rtol=0, atol=0)
        torch.testing.assert_close(light_b.intensity, light_a.intensity, rtol=0, atol=0)
        assert exported.has_geometry_maps(b.view) == source.has_geometry_maps(a.view)
        if source.has_geometry_maps(a.view):
            for map_a, map_b in zip(source.load_geometry_maps(a.view), exported.load_geometry_maps(b.view),
                                    strict=True):
                torch.testing.assert_close(map_b, map_a, rtol=0, atol=0)


def test_sparse_export_of_the_demo_round_trips(tmp_path):
    demo = embedded_dataset()
    source = OLATDataset(demo)
    selection = select_regime(source, "images=9", seed=0)
    out = tmp_path / "demo_sparse9"
    result = export_regime(demo, out, "images=9", split="train", seed=0)
    assert result.selection == selection and result.note is None
    exported = OLATDataset(out)
    assert len(exported) == 9 and result.images == {"train": 9, "test": len(OLATDataset(demo, "test"))}
    chosen = [source.observations[i].image_path.relative_to(source.root).as_posix() for i in selection.observations]
    _assert_same_images(source, exported, chosen)
    # only the chosen images and their views' maps were copied: 9 PNGs and 2 maps each of 9 distinct views
    assert len(selection.views) == 9
    assert sorted(p.name for p in (out / "train").iterdir() if p.suffix == ".png") == sorted(
        Path(c).name for c in chosen)
    assert len(list((out / "train").glob("*.npy"))) == 2 * 9
    test_source, test_export = OLATDataset(demo, "test"), OLATDataset(out, "test")
    _assert_same_images(test_source, test_export, list(_by_file(test_source)))
    record = json.loads((out / "subset.json").read_text())
    assert (record["regime"], record["seed"], record["split"]) == ("images=9", 0, "train")
    assert record["selection"] == selection.to_json()
    assert [p.name for p in tmp_path.iterdir()] == ["demo_sparse9"], "a staging folder was left behind"


def test_a_bad_regime_or_an_existing_folder_writes_nothing(tmp_path):
    demo = embedded_dataset()
    for bad in ("images=x9", "views=3", "images=100000"):
        with pytest.raises(ValueError, match="regime"):
            export_regime(demo, tmp_path / "new" / "out", bad)
    assert not any(tmp_path.iterdir())
    (tmp_path / "taken").mkdir()
    with pytest.raises(DataError, match="taken exists"):
        export_regime(demo, tmp_path / "taken", "images=9")
    assert not any((tmp_path / "taken").iterdir())


def test_export_keeps_per_frame_keys_and_drops_excluded_images(tmp_path):
    """Per-frame intrinsics and light intensities follow the kept images; images in exclude_list.txt are not copied;
    a capture with no test split says so."""
    source = OLATDataset(FORMATS / "object_full")
    result = export_regime(FORMATS / "object_full", tmp_path / "out", "all")
    assert len(source) == 4 and result.images == {"train": 4}
    assert "no transforms_test.json" in result.note
    exported = OLATDataset(tmp_path / "out")
    _assert_same_images(source, exported, list(_by_file(source)))
    frames = json.loads((tmp_path / "out" / "transforms_train.json").read_text())["frames"]
    assert [len(f["file_paths"]) for f in frames] == [2, 2]
    assert [f["fl_x"] for f in frames] == [9.5, 10.5]
    assert frames[0]["light_intensities"] == [[1.0, 0.9, 0.8], [1.0, 1.0, 0.8]]
    assert not (tmp_path / "out" / "train" / "r_000_l_001.png").exists()


def test_export_of_the_per_image_variant(tmp_path):
    source = OLATDataset(FORMATS / "nrhints")
    selection = select_regime(source, "images=2", seed=1)
    export_regime(FORMATS / "nrhints", tmp_path / "out", "images=2", seed=1)
    exported = OLATDataset(tmp_path / "out")
    chosen = [source.observations[i].image_path.relative_to(source.root).as_posix() for i in selection.observations]
    _assert_same_images(source, exported, chosen)
    assert len(json.loads((tmp_path / "out" / "transforms_train.json").read_text())["frames"]) == 2


def test_cli_subset(tmp_path, capsys):
    main(["subset", "--data", str(embedded_dataset()), "--regime", "views=2,lights=2", "--seed", "1",
          "--out", str(tmp_path / "out")])
    printed = capsys.readouterr().out
    assert "4 train images" in printed and "views=2,lights=2" in printed
    assert len(OLATDataset(tmp_path / "out")) == 4
    with pytest.raises(SystemExit) as exit_info:
        main(["subset", "--data", str(embedded_dataset()), "--regime", "images=9", "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert "exists" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
