"""``runtime.compile``: the compiled step computes what the eager one does (aot_eager on CPU: the graphs as traced;
inductor on CUDA: the fused kernels), and refuses unknown backends by key."""

from __future__ import annotations

import copy
import importlib.util

import pytest
import torch

from diamond_sss.data import OLATDataset
from diamond_sss.data.analytic import make_capture
from diamond_sss.training.overrides import make_config
from diamond_sss.training.run import train_run
from diamond_sss.training.trainer import ImageSource, Trainer

TINY = {"num_gaussians": 200, "batch_size": 2, "lambda_lpips": 0.0, "raytrace_gaussians": 32, "raytrace_every": 2,
        "mv_pixels_per_pair": 16, "mv_pairs_per_step": 1, "densify": False, "image_log_every": 1000,
        "sss_light_depth": 16, "sss_light_depth_every": 2, "sss_angular_inputs": True, "log_every": 1000}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("capture")
    make_capture(root, views=5, lights=2, size=16)
    return root


class GradientRecorder:
    """Stands in for an optimiser: keeps the gradients of its parameters at each step, changes nothing, so that two
    runs compare the same model at every step (an Adam step amplifies float rounding in near-zero gradients)."""

    def __init__(self, params) -> None:
        self.params = list(params)
        self.param_groups = [{"params": self.params, "lr": 0.0}]  # the trainer sets each step's rate here
        self.steps: list[list[torch.Tensor]] = []

    def step(self) -> None:
        self.steps.append([p.grad.detach().cpu().clone() for p in self.params])

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            p.grad = None


def _steps(capture, tmp_path, backend: str, device: str, steps: int = 3) -> tuple[list[dict], list]:
    """Loss terms and gradients of ``steps`` training steps of one seeded scene, which no optimiser moves (the
    batches, multi-view pairs and ray-traced Gaussians change from step to step)."""
    cfg = make_config("diamond", overrides={**TINY, "device": device, "compile": backend})
    trainer = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / backend, show_progress=False)
    scene = trainer.build_scene()
    recorders = {name: GradientRecorder(group["params"][0] for group in optimizer.param_groups)
                 for name, optimizer in trainer.build_optimizers(scene).items()}
    recorders["mlp"] = GradientRecorder(scene.mlp.parameters())
    terms = [{k: v.item() for k, v in trainer.training_step(scene, recorders, {}, step).items()}
             for step in range(steps)]
    assert scene.compiled_with == backend
    return terms, [grads for recorder in recorders.values() for grads in zip(*recorder.steps, strict=True)]


def _assert_same(eager, compiled, rtol: float, atol: float) -> None:
    for before, after in zip(eager[0], compiled[0], strict=True):
        assert before.keys() == after.keys()
        for name in before:
            assert after[name] == pytest.approx(before[name], rel=rtol, abs=atol), name
    for index, (expected, got) in enumerate(zip(eager[1], compiled[1], strict=True)):
        for step, (want, have) in enumerate(zip(expected, got, strict=True)):
            error = (have - want).norm() / want.norm().clamp_min(1e-12)
            assert error <= rtol, f"parameter {index}, step {step}: relative gradient error {error:.2e}"


def test_a_compiled_step_computes_the_eager_step(capture, tmp_path):
    """Every loss term (the multi-view and ray-traced ones, the light depth input included) and every gradient over
    three steps: the graphs dynamo traces around the rasterizer are the eager computation."""
    _assert_same(_steps(capture, tmp_path, "off", "cpu"), _steps(capture, tmp_path, "aot_eager", "cpu"),
                 rtol=5e-4, atol=1e-6)


def test_a_deep_copy_of_a_compiled_scene_renders_itself(capture, tmp_path):
    cfg = make_config("diamond", overrides={**TINY, "compile": "aot_eager"})
    trainer = Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False)
    scene = trainer.build_scene()
    scene.compile_shading("aot_eager")
    twin = copy.deepcopy(scene)
    with torch.no_grad():
        twin.gaussians.params["base_color"].fill_(3.0)
        dataset = OLATDataset(capture)
        camera, light = dataset.cameras[0], dataset.lights[0]
        args = (camera.w2c[None], camera.K[None], camera.width, camera.height, light.position[None],
                light.intensity[None])
        original, copied = scene.render(*args), twin.render(*args)
    assert not torch.allclose(original.gbuffer.base_color, copied.gbuffer.base_color)


def test_an_unknown_compile_backend_is_refused_by_key():
    with pytest.raises(ValueError, match="runtime.compile"):
        make_config("diamond", overrides={"compile": "triton"})


def test_inductor_without_its_compiler_is_refused_before_training_naming_the_key(capture, tmp_path, monkeypatch):
    from diamond_sss.utils import compiling

    monkeypatch.setattr(compiling.shutil, "which", lambda name: None)  # no C++ compiler on PATH
    cfg = make_config("diamond", overrides={**TINY, "device": "cpu", "compile": "inductor"})
    with pytest.raises(ValueError, match=r"runtime.compile' is 'inductor' but inductor on the CPU needs a C\+\+"):
        Trainer(cfg, [ImageSource(OLATDataset(capture))], tmp_path / "run", show_progress=False)
    with pytest.raises(ValueError, match="runtime.compile"):
        train_run(capture, tmp_path / "run", cfg)
    assert not (tmp_path / "run").exists()  # refused before the run folder is written
    assert compiling.compile_unavailable("aot_eager", torch.device("cpu")) is None


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="inductor on CUDA needs triton")
def test_inductor_on_cuda_computes_the_eager_step(capture, tmp_path):
    """The fused kernels (another summation order) agree with the eager step to float32 rounding."""
    _assert_same(_steps(capture, tmp_path, "off", "cuda"), _steps(capture, tmp_path, "inductor", "cuda"),
                 rtol=2e-3, atol=1e-5)
