"""The engine's device discipline: seeded streams on the data's device, no per-step sync, non-finite stops."""

from __future__ import annotations

import ast
import logging
import math
from pathlib import Path

import pytest
import torch

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.gaussians.model import nearest_neighbor_scales
from diamond_sss.training.checkpoint import checkpoint_folders
from diamond_sss.training.loss_log import LossLog
from diamond_sss.training.overrides import make_config
from diamond_sss.training.trainer import ImageSource, Trainer
from diamond_sss.utils import rng

SRC = Path(__file__).resolve().parents[1] / "src" / "diamond_sss"
RANDOM_FUNCTIONS = {"rand", "randn", "randint", "randperm", "normal", "multinomial", "bernoulli", "rand_like",
                    "randn_like", "randint_like"}
TINY = {
    "num_gaussians": 200, "batch_size": 2, "lambda_lpips": 0.0, "raytrace_gaussians": 32, "raytrace_every": 2,
    "mv_pixels_per_pair": 16, "mv_pairs_per_step": 1, "densify": False, "image_log_every": 1000, "device": "cpu",
}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("capture")
    make_capture(root, views=5, lights=2, size=16)
    return root


def test_streams_draw_on_the_generator_device_and_land_on_the_requested_one():
    generator = rng.stream_generator(3, 7, 1)
    assert generator.device.type == "cpu"
    expected = torch.randn(4, 3, generator=torch.Generator().manual_seed(rng.stream_seed(3, 7, 1)))
    on_meta = rng.randn(4, 3, generator=rng.stream_generator(3, 7, 1), device="meta")
    assert on_meta.device.type == "meta" and on_meta.shape == (4, 3)
    torch.testing.assert_close(rng.randn(4, 3, generator=generator), expected)
    assert rng.randperm(6, generator=rng.stream_generator(0, 0, 0), device="meta").dtype == torch.int64
    assert rng.randint(5, 3, generator=rng.stream_generator(0, 0, 0)).tolist() == torch.randint(
        5, (3,), generator=torch.Generator().manual_seed(rng.stream_seed(0, 0, 0))).tolist()
    assert rng.rand(2, device="cpu").device.type == "cpu"
    assert rng.stream_seed(1, 2, 3) == (1_000_003 + 2) * 16 + 3
    with pytest.raises(ValueError, match="stream"):
        rng.stream_seed(0, 0, 16)


def _random_calls_with_generator_and_device(path: Path) -> list[int]:
    lines = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"):
            keywords = {k.arg for k in node.keywords}
            if node.func.attr in RANDOM_FUNCTIONS and {"generator", "device"} <= keywords:
                lines.append(node.lineno)
    return lines


def test_only_the_rng_module_pairs_a_generator_with_a_device():
    """torch refuses a generator of another device than the draw's (CUDA: 'Expected a cuda device type for
    generator'); a draw that names both is made in utils/rng.py, which draws on the generator's device."""
    offenders = {
        str(path.relative_to(SRC)): lines
        for path in SRC.rglob("*.py")
        if path.name != "rng.py" and (lines := _random_calls_with_generator_and_device(path))
    }
    assert offenders == {}
    bad = "import torch\ntorch.randn(3, generator=g, device=d)\n"
    probe = SRC.parent.parent / "tests" / "_probe_rng.py"
    try:
        probe.write_text(bad)
        assert _random_calls_with_generator_and_device(probe) == [2]
    finally:
        probe.unlink()


def test_loss_log_reads_once_and_names_the_first_non_finite_step():
    log = LossLog()
    log.record(0, {"l1": torch.tensor(0.5), "total": torch.tensor(0.5)})
    log.record(1, {"l1": torch.tensor(0.25), "raytrace": torch.tensor(0.1), "total": torch.tensor(0.35)})
    assert log.flush() == pytest.approx({"l1": 0.25, "raytrace": 0.1, "total": 0.35})
    assert log.flush() == {}
    log.record(4, {"l1": torch.tensor(0.5)})
    log.record(5, {"l1": torch.tensor(0.5), "mask": torch.tensor(math.nan)})
    log.record(6, {"l1": torch.tensor(math.inf)})
    with pytest.raises(FloatingPointError, match=r"step 5: mask"):
        log.flush()


class _NaNTrainer(Trainer):
    """Its mask term turns NaN at step ``nan_at``."""

    nan_at = 3

    def training_step(self, scene, optimizers, strategy_state, step):
        values = super().training_step(scene, optimizers, strategy_state, step)
        if step == self.nan_at:
            values["mask"] = torch.tensor(math.nan)
        return values


def test_training_stops_at_a_non_finite_loss_and_keeps_the_last_good_checkpoint(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "iterations": 8, "checkpoint_every": 2, "log_every": 5})
    trainer = _NaNTrainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False)
    with pytest.raises(FloatingPointError, match=r"step 3: mask"):
        trainer.run()
    assert checkpoint_folders(tmp_path / "run")[0].name.endswith("2")
    assert not (tmp_path / "run" / "model.safetensors").exists()


def test_resume_without_a_checkpoint_says_so(capture, tmp_path, caplog):
    cfg = make_config("diamond", overrides={**TINY, "iterations": 1, "log_every": 1})
    trainer = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False)
    with caplog.at_level(logging.WARNING, logger="diamond_sss.training.trainer"):
        trainer.run(resume=True)  # a new folder: nothing to say
        assert "no checkpoint" not in caplog.text
        (tmp_path / "run" / "model.safetensors").unlink()  # an earlier run that left no checkpoint
        trainer.run(resume=True)
    assert "no checkpoint" in caplog.text and "step 0" in caplog.text


def test_training_step_returns_device_tensors_without_reading_them(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "iterations": 2})
    trainer = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False)
    scene = trainer.build_scene()
    values = trainer.training_step(scene, trainer.build_optimizers(scene), {}, 0)
    assert {"raytrace", "mv_silhouette", "total"} <= values.keys()
    assert all(torch.is_tensor(v) and v.device == trainer.device and v.ndim == 0 for v in values.values())


def test_nearest_neighbour_scales_match_brute_force_with_duplicates():
    points = torch.randn(1500, 3, generator=torch.Generator().manual_seed(4))
    points[10] = points[11]  # a duplicate: its nearest neighbour is at distance 0 (clamped to 1e-7)
    dists = torch.cdist(points.double(), points.double()) + torch.eye(1500, dtype=torch.float64) * 1e9
    expected = dists.topk(3, largest=False).values.square().mean(dim=1).clamp_min(1e-7).sqrt().float()
    torch.testing.assert_close(nearest_neighbor_scales(points), expected)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_the_diamond_preset_with_every_term_trains_on_cuda(capture, tmp_path):
    """The `diamond` preset with every term on (ray-traced visibility each step, multi-view losses)."""
    cfg = make_config("diamond", overrides={**TINY, "device": "cuda", "iterations": 4, "log_every": 2,
                                           "raytrace_every": 1, "densify": True, "densify_from_iter": 1,
                                           "densification_interval": 2})
    result = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False).run()
    assert math.isfinite(result.final_loss)
    assert {"raytrace", "mv_silhouette", "mv_depth"} <= result.history[-1].keys()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("multiview", [False, True], ids=["plain", "multiview"])
def test_a_training_step_on_cuda_queues_without_waiting_for_the_gpu(capture, tmp_path, monkeypatch, multiview):
    """Batch upload, render, losses, backward pass and optimisers between two ray-tracing steps with CUDA's sync
    debugging set to raise on any host sync (a sync stops the host queueing the next kernels ahead of the GPU), except
    inside ``gsplat.rasterization``: its tile intersection sizes its buffer on the host, one sync per call by design."""
    import gsplat

    overrides = {**TINY, "device": "cuda", "raytrace_every": 1000, "log_every": 1000}
    if not multiview:
        overrides.update(lambda_sil=0.0, lambda_depth=0.0)
    trainer = Trainer(make_config("diamond", overrides=overrides), [ImageSource(OLATDataset(capture))],
                      tmp_path / "run", show_progress=False)
    scene = trainer.build_scene()
    optimizers = trainer.build_optimizers(scene)
    state = trainer._initial_strategy_state()
    for step in range(4):  # ray tracing at step 0; every light's maps made
        trainer.training_step(scene, optimizers, state, step)
    rasterization, rasterizer_calls = gsplat.rasterization, []

    def rasterization_free_to_sync(*args, **kwargs):
        rasterizer_calls.append(torch.cuda.get_sync_debug_mode())
        torch.cuda.set_sync_debug_mode("default")
        try:
            return rasterization(*args, **kwargs)
        finally:
            torch.cuda.set_sync_debug_mode(rasterizer_calls[-1])

    monkeypatch.setattr(gsplat, "rasterization", rasterization_free_to_sync)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        terms = trainer.training_step(scene, optimizers, state, 4)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert torch.isfinite(terms["total"]).item()
    assert ("mv_silhouette" in terms) == multiview
    assert rasterizer_calls and set(rasterizer_calls) == {2}  # the step rasterized, under the "error" mode


@pytest.mark.parametrize("value", [-0.5, float("nan")])
def test_synthetic_weight_is_checked_in_the_config_not_in_the_step(value):
    from diamond_sss.pipeline.config import PipelineConfig
    from diamond_sss.pipeline.run import checked_config

    with pytest.raises(ValueError, match="synthetic_weight"):
        checked_config(PipelineConfig(synthetic_weight=value))


def test_epoch_order_is_a_permutation_drawn_once_per_epoch():
    from diamond_sss.data.dataset import seeded_epoch_indices

    order = [seeded_epoch_indices(step, 1, 7, seed=3)[0] for step in range(14)]
    assert sorted(order[:7]) == sorted(order[7:]) == list(range(7)) and order[:7] != order[7:]
    assert seeded_epoch_indices(2, 3, 7, seed=3) == order[6:9]


def test_resume_with_other_settings_is_refused_naming_them(tmp_path, caplog):
    from diamond_sss.data.analytic import make_capture
    from diamond_sss.data.dataset import OLATDataset
    from diamond_sss.training.overrides import make_config
    from diamond_sss.training.run_folder import changed_settings
    from diamond_sss.training.trainer import ImageSource, Trainer

    make_capture(tmp_path / "data", views=4, lights=2, size=16)
    sources = [ImageSource(OLATDataset(tmp_path / "data", "train"))]
    base = {"iterations": 2, "num_gaussians": 50, "batch_size": 1, "checkpoint_every": 1, "lambda_lpips": 0.0,
            "densify": False}
    Trainer(make_config("diamond", overrides=base), sources, tmp_path / "run", show_progress=False).run()
    longer = make_config("diamond", overrides={**base, "iterations": 3})
    assert changed_settings(tmp_path / "run", longer) == {}  # a longer run may resume
    Trainer(longer, sources, tmp_path / "run", show_progress=False).run(resume=True)
    summary = tmp_path / "run" / "train_summary.json"
    written = summary.stat().st_mtime_ns
    again = Trainer(longer, sources, tmp_path / "run", show_progress=False)
    with caplog.at_level(logging.INFO, logger="diamond_sss.training.trainer"):
        result = again.run(resume=True)  # finished: nothing is retrained or rewritten
    assert "already trained for 3 steps" in caplog.text and summary.stat().st_mtime_ns == written
    assert result.steps == 3 and again.scene.gaussians.num_gaussians == 50
    wider = make_config("diamond", overrides={**base, "iterations": 3, "sss_width": 16})
    with pytest.raises(ValueError, match=r"other settings \(sss_width: 32 -> 16\)"):
        Trainer(wider, sources, tmp_path / "run", show_progress=False).run(resume=True)
