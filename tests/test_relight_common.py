"""Shared diffusion utilities: output cache, hashing, DDIM loop, checkpoints."""

from __future__ import annotations

import pytest
import torch

from diamond_sss.diffusion.common.cache import OutputCache
from diamond_sss.diffusion.common.checkpoints import (
    latest_accelerate_checkpoint,
    load_accelerate_checkpoint,
    save_accelerate_checkpoint,
)
from diamond_sss.diffusion.common.hashing import files_hash, state_dict_hash
from diamond_sss.diffusion.common.runtime import (
    Deadline,
    deterministic_kernels,
    fused_adamw,
    make_accelerator,
)
from diamond_sss.diffusion.common.sampling import ddim_sample
from diamond_sss.diffusion.common.schedulers import SchedulerConfig, make_ddim_scheduler


def test_cache_entries_are_keyed_and_atomic(tmp_path):
    cache = OutputCache(tmp_path)
    key = cache.key({"model": "abc", "input": [1, 2]})
    assert key == cache.key({"input": [1, 2], "model": "abc"}) and key != cache.key(
        {"model": "abd", "input": [1, 2]}
    )
    assert cache.get(key) is None

    def failing(folder):
        (folder / "half.txt").write_text("x")
        raise RuntimeError("crash")

    with pytest.raises(RuntimeError):
        cache.put(key, failing)
    assert cache.get(key) is None and not list(tmp_path.rglob("*.tmp"))
    calls = []
    entry, hit = cache.get_or_create(
        key, lambda folder: (calls.append(1), (folder / "a.txt").write_text("1"))
    )
    assert not hit and (entry / "a.txt").read_text() == "1"
    again, hit = cache.get_or_create(key, lambda folder: calls.append(1))
    assert hit and again == entry and calls == [1]


def test_hashes_follow_content(tmp_path):
    a = {"w": torch.ones(2, 2)}
    assert state_dict_hash(a) == state_dict_hash({"w": torch.ones(2, 2)})
    assert state_dict_hash(a) != state_dict_hash({"w": torch.ones(2, 2) * 2})
    assert state_dict_hash(a) != state_dict_hash({"w": torch.ones(4)})
    (tmp_path / "config.json").write_text("{}")
    first = files_hash(tmp_path)
    (tmp_path / "config.json").write_text("{ }")
    assert files_hash(tmp_path) != first
    with pytest.raises(FileNotFoundError):
        files_hash(tmp_path / "missing")


def test_ddim_with_an_exact_denoiser_recovers_the_target():
    """A denoiser that returns the true velocity towards ``x0`` makes DDIM land on ``x0``."""
    scheduler = make_ddim_scheduler(SchedulerConfig())
    alphas = scheduler.alphas_cumprod
    x0 = torch.linspace(-0.8, 0.8, 12).reshape(1, 3, 2, 2)

    def denoise(x, t):
        a = alphas[t].sqrt().reshape(-1, 1, 1, 1)
        s = (1 - alphas[t]).sqrt().reshape(-1, 1, 1, 1)
        eps = (x - a * x0) / s.clamp_min(1e-6)
        return a * eps - s * x0

    out = ddim_sample(denoise, (1, 3, 2, 2), scheduler, 10, torch.Generator().manual_seed(0))
    assert torch.allclose(out, x0, atol=1e-3)
    noise = torch.randn(1, 3, 2, 2, generator=torch.Generator().manual_seed(0))
    assert torch.equal(
        ddim_sample(lambda x, t: torch.zeros_like(x), (1, 3, 2, 2), scheduler, 3, noise=noise),
        ddim_sample(
            lambda x, t: torch.zeros_like(x), (1, 3, 2, 2), scheduler, 3, torch.Generator().manual_seed(0)
        ),
    )
    with pytest.raises(ValueError, match="num_steps"):
        ddim_sample(denoise, (1, 3, 2, 2), scheduler, 0)


def test_checkpoints_are_complete_and_pruned(tmp_path):
    accelerator = make_accelerator()
    model = accelerator.prepare(torch.nn.Linear(2, 2))
    for step in (1, 2, 3):
        save_accelerate_checkpoint(accelerator, tmp_path, step, extra={"note": step}, keep=2)
    assert [p.name for p in sorted(tmp_path.iterdir())] == ["step_00000002", "step_00000003"]
    (tmp_path / "step_00000009").mkdir()  # incomplete: no extra.json
    assert latest_accelerate_checkpoint(tmp_path).name == "step_00000003"
    saved = model.weight.detach().clone()
    with torch.no_grad():
        model.weight.zero_()
    assert load_accelerate_checkpoint(accelerator, tmp_path / "step_00000003") == {"step": 3, "note": 3}
    assert torch.equal(model.weight, saved)


def test_accelerators_with_other_settings_follow_one_another():
    """Fine-tunes run one after another in one process with other precisions (accelerate refuses that)."""
    assert make_accelerator("bf16").mixed_precision == "bf16"
    assert make_accelerator("no").mixed_precision == "no"
    assert make_accelerator("no").device.type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_deterministic_kernels_are_scoped_to_the_call():
    seen = {}

    @deterministic_kernels
    def body():
        seen["inside"] = (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic,
                          torch.is_deterministic_algorithms_warn_only_enabled())
        raise RuntimeError("fails inside")

    before = (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic)
    with pytest.raises(RuntimeError, match="fails inside"):
        body()
    assert seen["inside"] == (True, True, False)  # warn-only would let CUDA attention keep a random backward
    assert (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic) == before


def test_autotuned_kernel_settings_are_scoped_to_the_block():
    from diamond_sss.diffusion.common.runtime import kernel_settings

    def current():
        return (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.deterministic,
                torch.backends.cudnn.benchmark)

    before = current()
    with kernel_settings(deterministic=True):
        with pytest.raises(RuntimeError, match="fails inside"), kernel_settings(deterministic=False):
            assert current() == (False, False, True)
            raise RuntimeError("fails inside")
        assert current() == (True, True, False)
    assert current() == before


def test_a_deadline_passes_only_once_its_seconds_are_spent_and_refuses_bad_limits():
    assert not Deadline(None).passed() and not Deadline(3600.0).passed()
    spent = Deadline(0.0)
    while spent.elapsed() <= 0.0:
        pass
    assert spent.passed()
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=f"time_limit_s must be a finite number of seconds >= 0 or None, got {bad}"):
            Deadline(bad)



def test_the_fused_adamw_makes_the_update_of_the_reference_adamw():
    torch.manual_seed(0)
    start = [torch.randn(5, 3), torch.randn(7)]
    grads = [[torch.randn_like(p) for p in start] for _ in range(3)]
    fused = [p.clone().requires_grad_(True) for p in start]
    reference = [p.clone().requires_grad_(True) for p in start]
    optimizers = [fused_adamw(fused, 1e-2, 0.1), torch.optim.AdamW(reference, 1e-2, weight_decay=0.1, foreach=False)]
    assert optimizers[0].defaults["fused"] is True
    for step_grads in grads:
        for params, optimizer in zip((fused, reference), optimizers, strict=True):
            for p, g in zip(params, step_grads, strict=True):
                p.grad = g.clone()
            optimizer.step()
    for a, b, s0 in zip(fused, reference, start, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
        assert (a - s0).abs().min() > 1e-3  # three steps of lr 1e-2 moved every entry
