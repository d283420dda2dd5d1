"""The capped densification strategy (``training/densify.py``): known counts on a hand-made Gaussian set."""

from __future__ import annotations

import torch
from gsplat.strategy import DefaultStrategy

from diamond_sss.training.densify import CappedStrategy


def _gaussians(opacity_logits: list[float]) -> tuple[torch.nn.ParameterDict, dict[str, torch.optim.Optimizer]]:
    n = len(opacity_logits)
    generator = torch.Generator().manual_seed(0)
    params = torch.nn.ParameterDict({
        "means": torch.randn(n, 3, generator=generator),
        "scales": torch.full((n, 3), -6.0),  # small: every grown Gaussian is duplicated, not split
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        "opacities": torch.tensor(opacity_logits),
    })
    optimizers = {name: torch.optim.Adam([param], lr=1e-3) for name, param in params.items()}
    for name, param in params.items():  # one step, so that the Adam moments exist and must follow the edits
        param.grad = torch.zeros_like(param)
        optimizers[name].step()
    return params, optimizers


def _refine(strategy: DefaultStrategy, params, optimizers, state, step: int) -> None:
    """One refinement step in which every Gaussian was seen with a large screen-space gradient."""
    n = len(params["means"])
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.ones(1, n, 2)
    info = {"means2d": means2d, "width": 10, "height": 10, "n_cameras": 1, "radii": torch.ones(1, n, 2),
            "gaussian_ids": None}
    strategy.step_post_backward(params, optimizers, state, step, info, packed=False)


def test_refinements_never_pass_the_cap_and_keep_pruning_at_it():
    strategy = CappedStrategy(max_count=15, grow_grad2d=1e-3, refine_start_iter=0, refine_every=1,
                              refine_stop_iter=100, reset_every=1000, pause_refine_after_reset=0, prune_opa=0.005,
                              verbose=False)
    logits = [float(v) for v in torch.linspace(-2.0, 2.0, 10)]
    params, optimizers = _gaussians(logits)
    state = strategy.initialize_state(scene_scale=1.0)

    _refine(strategy, params, optimizers, state, step=1)  # 10 duplicated into 20: the 5 of lowest opacity go
    assert len(params["means"]) == 15
    kept = sorted(params["opacities"].detach().tolist())
    assert kept == sorted(logits + logits)[5:]
    assert all(len(group["params"][0]) == 15 for opt in optimizers.values() for group in opt.param_groups)
    assert all(len(opt.state[opt.param_groups[0]["params"][0]]["exp_avg"]) == 15 for opt in optimizers.values())

    with torch.no_grad():
        params["opacities"][:4] = -10.0  # fall under prune_opa at the cap
    _refine(strategy, params, optimizers, state, step=2)  # at the cap: no growth, but the pruning goes on
    assert len(params["means"]) == 11

    _refine(strategy, params, optimizers, state, step=3)  # under the cap again: grows back to it, not past
    assert len(params["means"]) == 15


def test_under_the_cap_it_grows_as_gsplat_does():
    settings = {"grow_grad2d": 1e-3, "refine_start_iter": 0, "refine_every": 1, "refine_stop_iter": 100,
                "reset_every": 1000, "pause_refine_after_reset": 0, "verbose": False}
    grown = []
    for strategy in (CappedStrategy(max_count=100, **settings), DefaultStrategy(**settings)):
        params, optimizers = _gaussians([0.0] * 6)
        _refine(strategy, params, optimizers, strategy.initialize_state(scene_scale=1.0), step=1)
        grown.append((params, optimizers))
    (params, optimizers), (reference, reference_optimizers) = grown
    assert len(params["means"]) == 12  # every small Gaussian duplicated once, in place, none pruned
    for name, param in params.items():
        assert torch.equal(param[6:], param[:6]) and torch.equal(param, reference[name]), name
        moments, expected = optimizers[name].state[param], reference_optimizers[name].state[reference[name]]
        assert torch.equal(moments["exp_avg"], expected["exp_avg"])
