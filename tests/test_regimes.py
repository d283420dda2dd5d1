"""Capture regimes: counts, determinism, farthest-point spread, the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from diamond_sss.cli.main import main
from diamond_sss.data import OLATDataset, select_regime
from diamond_sss.data.analytic import make_capture
from diamond_sss.data.dataset import directions_from
from diamond_sss.data.regimes import farthest_point_order, resolve_count


@pytest.fixture(scope="module")
def lattice(tmp_path_factory):
    root = tmp_path_factory.mktemp("lattice")
    make_capture(root, views=20, lights=12, size=8)
    return root


def test_resolve_count():
    assert resolve_count("5%", 100, "views") == 5
    assert resolve_count("5%", 10, "views") == 1  # max(1, round(0.5)) with round-half-even -> 1
    assert resolve_count("3%", 112, "lights") == 3
    assert resolve_count("5", 5, "views") == 5
    assert resolve_count("all", 9, "views") == 9
    with pytest.raises(ValueError, match="'lights=7' asks for 7 lights; the capture has 5"):
        resolve_count("7", 5, "lights")
    for bad in ("0", "-1", "x%", "150%", "abc"):
        with pytest.raises(ValueError, match="views"):
            resolve_count(bad, 10, "views")


def test_farthest_point_second_pick_is_the_antipode():
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    order = farthest_point_order(dirs, 5, torch.Generator().manual_seed(3))
    assert len(set(order)) == 5
    assert order[1] == int(torch.argmax((dirs - dirs[order[0]]).norm(dim=-1)))
    # each pick maximises the distance to the set chosen before it
    for k in range(2, 5):
        chosen = dirs[order[:k]]
        gaps = torch.cdist(dirs, chosen).min(dim=1).values
        assert gaps[order[k]] == pytest.approx(float(gaps.max()))


def test_fps_spreads_better_than_random(lattice):
    ds = OLATDataset(lattice)
    dirs = directions_from(ds.camera_centers, ds.bounds.center)
    fps = select_regime(ds, "views=5,lights=all", seed=0).views
    fps_gap = torch.pdist(dirs[fps]).min()
    random_gaps = [torch.pdist(dirs[torch.randperm(20, generator=torch.Generator().manual_seed(s))[:5]]).min()
                   for s in range(20)]
    assert fps_gap >= torch.stack(random_gaps).median()


@pytest.mark.parametrize("spec,views,lights,images", [
    ("all", 20, 12, 240),
    ("views=10%,lights=25%", 2, 3, 6),
    ("views=5,lights=6", 5, 6, 30),
    ("views=all,lights=1", 20, 1, 20),
])
def test_regime_counts(lattice, spec, views, lights, images):
    selection = select_regime(OLATDataset(lattice), spec, seed=1)
    assert (len(selection.views), len(selection.lights), len(selection.observations)) == (views, lights, images)


def test_regime_larger_than_the_capture_is_an_error(lattice):
    ds = OLATDataset(lattice)
    with pytest.raises(ValueError, match="'views=500' asks for 500 views; the capture has 20"):
        select_regime(ds, "views=500,lights=3")
    with pytest.raises(ValueError, match="'lights=13' asks for 13 lights; the capture has 12"):
        select_regime(ds, "views=3,lights=13")
    with pytest.raises(ValueError, match="'images=241' asks for 241 images; the capture has 240"):
        select_regime(ds, "images=241")
    assert len(select_regime(ds, "views=20,lights=12").observations) == 240
    assert len(select_regime(ds, "images=240").observations) == 240


def test_cli_regime_larger_than_the_capture(lattice, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["regimes", "--data", str(lattice), "--regime", "views=21,lights=1"])
    assert exit_info.value.code == 2
    assert "asks for 21 views; the capture has 20" in capsys.readouterr().err


def test_all_views_one_light_spreads_lights(lattice):
    ds = OLATDataset(lattice)
    selection = select_regime(ds, "all-views-1-light", seed=2)
    chosen = [ds.observations[i] for i in selection.observations]
    assert sorted(o.view for o in chosen) == list(range(20))
    counts = torch.bincount(torch.tensor([o.light for o in chosen]), minlength=12)
    assert int(counts.max()) - int(counts.min()) <= 1


def test_images_regime_spreads_jointly(lattice):
    ds = OLATDataset(lattice)
    selection = select_regime(ds, "images=10", seed=0)
    assert len(selection.observations) == 10
    assert len(selection.views) >= 5 and len(selection.lights) >= 5


def test_only_existing_observations_are_used(lattice):
    ds = OLATDataset(lattice)
    sparse = ds.subset([i for i, o in enumerate(ds.observations) if (o.view + o.light) % 2 == 0])
    selection = select_regime(sparse, "views=all,lights=all", seed=0)
    assert len(selection.observations) == len(sparse)
    selection = select_regime(sparse, "all-views-1-light", seed=0)
    assert all((sparse.observations[i].view + sparse.observations[i].light) % 2 == 0
               for i in selection.observations)


def test_views_and_lights_are_picked_captured_together():
    """On a lattice with missing images, independent picks may share no image; the regime picks a view and a light
    that were captured together, for every seed."""
    ds = OLATDataset(Path(__file__).parent / "fixtures" / "formats" / "object_full")
    assert not ds.presence.all()
    for seed in range(8):
        selection = select_regime(ds, "views=1,lights=1", seed)
        assert len(selection.observations) == 1 and ds.presence[selection.views[0], selection.lights[0]]
        assert selection.note is None


def _half_lattice(ds: OLATDataset, seed: int = 0) -> OLATDataset:
    """``ds`` with each view lit by a seeded random half of the lights (an incomplete lattice)."""
    generator = torch.Generator().manual_seed(seed)
    lit = {view: set(torch.randperm(ds.num_lights, generator=generator)[: ds.num_lights // 2].tolist())
           for view in range(ds.num_views)}
    return ds.subset([i for i, obs in enumerate(ds.observations) if obs.light in lit[obs.view]])


def test_an_incomplete_lattice_gives_the_full_views_x_lights(lattice):
    """Each of 20 views lit by 6 of 12 lights: 3 views x 3 lights picked independently share all 9 images with
    probability 1/512; picked together they do, for every seed, and the picks stay spread and seeded."""
    half = _half_lattice(OLATDataset(lattice))
    selections = [select_regime(half, "views=3,lights=3", seed) for seed in range(10)]
    for selection in selections:
        assert (len(selection.views), len(selection.lights), len(selection.observations)) == (3, 3, 9)
        assert half.presence[selection.views][:, selection.lights].all() and selection.note is None
        assert {(half.observations[i].view, half.observations[i].light) for i in selection.observations} == {
            (v, l) for v in selection.views for l in selection.lights}
    assert len({(tuple(s.views), tuple(s.lights)) for s in selections}) >= 3, "the seed does not vary the picks"
    assert select_regime(half, "views=3,lights=3", 4) == selections[4]
    assert select_regime(half, "views=all,lights=1", 0).observations  # a light seen by some views: those images


def test_when_no_full_views_x_lights_exists_the_note_says_so(lattice, capsys):
    """5 views sharing 6 given lights among 6 of 12 per view: chance 1/924 per view, so none of 20 does. The
    selection maximises the captured pairs given its lights (the 5 views seeing most of them) and says how many."""
    half = _half_lattice(OLATDataset(lattice))
    selection = select_regime(half, "views=5,lights=6", seed=0)
    pairs = half.presence[selection.views][:, selection.lights]
    assert len(selection.views) == 5 and len(selection.lights) == 6
    assert len(selection.observations) == int(pairs.sum()) < 30
    coverage = half.presence[:, selection.lights].sum(1)
    assert int(pairs.sum()) == int(coverage.topk(5).values.sum()), "another 5 views see more of these lights"
    assert selection.note.startswith(f"{len(selection.observations)} of 5 x 6 = 30 images")
    assert "incomplete lattice" in selection.note
    assert selection.to_json() == {"spec": "views=5,lights=6", "seed": 0, "views": selection.views,
                                   "lights": selection.lights, "observations": selection.observations,
                                   "note": selection.note, "images": len(selection.observations)}


def test_cli_prints_the_note_of_an_incomplete_lattice(tmp_path, capsys):
    make_capture(tmp_path, views=6, lights=6, size=8)
    path = tmp_path / "transforms_train.json"
    payload = json.loads(path.read_text())
    for view, frame in enumerate(payload["frames"]):  # view v lit by lights v, v+1, v+2 (mod 6): no 2 views share 3
        keep = [k for k in range(6) if (k - view) % 6 < 3]
        for key in ("file_paths", "light_positions", "light_intensities"):
            frame[key] = [frame[key][k] for k in keep]
    path.write_text(json.dumps(payload))
    main(["regimes", "--data", str(tmp_path), "--regime", "views=2,lights=3", "--json"])
    chosen = json.loads(capsys.readouterr().out)
    # the best: two overlapping windows, e.g. lights {0, 1, 2} in views 0 ({0, 1, 2}) and 1 ({1, 2, 3}): 3 + 2
    assert chosen["images"] == 5 and chosen["note"].startswith("5 of 2 x 3 = 6 images")
    main(["regimes", "--data", str(tmp_path), "--regime", "views=2,lights=3"])
    assert "5 of 2 x 3 = 6 images" in capsys.readouterr().out


def test_determinism_and_bad_specs(lattice):
    ds = OLATDataset(lattice)
    assert select_regime(ds, "views=25%,lights=25%", 4) == select_regime(ds, "views=25%,lights=25%", 4)
    assert select_regime(ds, "views=25%,lights=25%", 4) != select_regime(ds, "views=25%,lights=25%", 5)
    for bad in ("views=5", "lights=2,views=2,images=3", "foo", "views=5,light=2"):
        with pytest.raises(ValueError, match="regime"):
            select_regime(ds, bad)


def test_cli_regimes_and_info_json(lattice, capsys):
    main(["regimes", "--data", str(lattice), "--regime", "views=5%,lights=5%", "--seed", "3", "--json"])
    first = json.loads(capsys.readouterr().out)
    main(["regimes", "--data", str(lattice), "--regime", "views=5%,lights=5%", "--seed", "3", "--json"])
    assert json.loads(capsys.readouterr().out) == first
    assert first["images"] == len(first["observations"]) == 1
    main(["info", "--data", str(lattice), "--json"])
    summary = json.loads(capsys.readouterr().out)
    assert (summary["views"], summary["lights"], summary["images"], summary["width"], summary["height"]) == (
        20, 12, 240, 8, 8)


def test_cli_reports_bad_input_without_traceback(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["info", "--data", str(tmp_path / "nope")])
    assert exit_info.value.code == 2
    assert "data folder not found" in capsys.readouterr().err
