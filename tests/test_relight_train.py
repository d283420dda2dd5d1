"""Relighting fine-tuning: sample selection (<= 7%), one-sample overfit, losses, EMA, exact resume."""

from __future__ import annotations

import json
from collections import Counter

import pytest
import torch
from test_relight_model import tiny_model

from diamond_sss.data.dataset import OLATDataset
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.data.errors import DataError
from diamond_sss.diffusion.common.ema import EMA, EMA_FILE
from diamond_sss.diffusion.relight.data import load_finetune_views, load_relight_views
from diamond_sss.diffusion.relight.losses import RelightLossWeights, low_frequency_l1
from diamond_sss.diffusion.relight.model import RelightDiffusion
from diamond_sss.diffusion.relight.train import RelightTrainConfig, finetune, lr_factor, training_loss
from diamond_sss.errors import DamagedFileError
from diamond_sss.utils.io import load_safetensors


@pytest.fixture(scope="module")
def views():
    return load_relight_views([embedded_dataset("finetune/torus_jade")], resolution=16)


def test_finetune_selection_is_recorded_and_small():
    selection = load_finetune_views(resolution=16).selection
    assert len(selection["fraction_of_capture"]) == 4
    assert all(0 < f <= 0.07 for f in selection["fraction_of_capture"].values())
    objects = {record["object"] for record in selection["images"]}
    assert objects == set(selection["fraction_of_capture"])
    with pytest.raises(DataError, match="more than 1%"):
        load_relight_views([embedded_dataset("finetune/torus_jade")], resolution=16, max_fraction=0.01)


def test_batches_fix_the_view_and_change_the_light(views):
    view, source, target = views.random_indices(64, torch.Generator().manual_seed(0))
    assert bool((source != target).all())
    batch = views.batch(view, source, target)
    assert batch["conditioning"].shape == (64, 8, 16, 16)
    # The conditioning's geometry channels are those of the sample's view, whatever the lights.
    assert torch.equal(batch["conditioning"][:, 3:], views.maps[view])
    assert torch.equal(batch["target"], views.images[view, target])


def test_views_with_few_lights_are_used_and_padding_never_drawn():
    # torus_jade holds a relighting subset (views x 10 lights) and a novel-view subset (views x 3 lights).
    root = embedded_dataset("finetune/torus_jade")
    views = load_relight_views([root], resolution=16)
    per_view = Counter(obs.view for obs in OLATDataset(root).observations)
    assert sorted(views.light_counts.tolist()) == sorted(per_view.values())
    assert 3 in per_view.values() and len(views.selection["images"]) == sum(per_view.values())
    view, source, target = views.random_indices(4000, torch.Generator().manual_seed(1))
    counts = views.light_counts[view]
    assert bool((source != target).all()) and bool((source < counts).all()) and bool((target < counts).all())
    # Uniform over ordered pairs: a 3-light view is drawn with probability 6 / sum_v c_v (c_v - 1).
    pairs = sum(c * (c - 1) for c in per_view.values())
    few = sum(c * (c - 1) for c in per_view.values() if c == 3) / pairs
    assert float((counts == 3).float().mean()) == pytest.approx(few, abs=0.03)
    with pytest.raises(ValueError, match="min_lights"):
        load_relight_views([embedded_dataset("finetune/torus_jade")], resolution=16, min_lights=1)


def test_low_frequency_term_ignores_high_frequencies():
    base = torch.zeros(1, 3, 8, 8)
    checker = (torch.arange(8)[:, None] + torch.arange(8)[None]) % 2 * 2.0 - 1.0
    assert float(low_frequency_l1(base + checker, base, 4)) == pytest.approx(0.0, abs=1e-6)
    assert float(low_frequency_l1(base + 0.5, base, 4)) == pytest.approx(0.5)


def test_one_sample_is_overfit(views):
    torch.manual_seed(0)
    model = tiny_model()
    batch = views.batch(torch.tensor([0]), torch.tensor([0]), torch.tensor([3]))
    weights = RelightLossWeights(ssim=0.0, cycle=0.0)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss, terms = training_loss(model, batch, weights, torch.Generator().manual_seed(0), with_cycle=False)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(terms["l1"])
    assert losses[-1] < 0.25 * losses[0]


def test_cycle_term_is_computed(views):
    batch = views.batch(torch.tensor([0, 1]), torch.tensor([0, 2]), torch.tensor([3, 4]))
    loss, terms = training_loss(
        tiny_model(), batch, RelightLossWeights(), torch.Generator().manual_seed(0), with_cycle=True
    )
    assert set(terms) == {"v_mse", "l1", "ssim", "low_frequency", "cycle"}
    assert bool(torch.isfinite(loss))


def test_lr_schedule():
    assert lr_factor(0, 10, 100) == pytest.approx(0.1)
    assert lr_factor(9, 10, 100) == pytest.approx(1.0)
    assert lr_factor(100, 10, 100) == pytest.approx(0.1)


def test_ema_tracks_and_restores():
    model = torch.nn.Linear(2, 1)
    ema = EMA(model, decay=0.5)
    before = model.weight.detach().clone()
    with torch.no_grad():
        model.weight.add_(1.0)
    ema.update(model)  # warm-up decay min(0.5, 1/10) = 0.1
    assert torch.allclose(ema.shadow["weight"], before + 0.9)
    with ema.averaged(model):
        assert torch.allclose(model.weight, before + 0.9)
    assert torch.allclose(model.weight, before + 1.0)


def test_resume_continues_exactly(views, tmp_path):
    config = RelightTrainConfig(steps=3, batch_size=2, checkpoint_every=1, log_every=1, cycle_every=2)
    straight = finetune(views, tmp_path / "straight", tiny_model(), config)
    stopped = RelightTrainConfig(**{**config.__dict__, "time_limit_s": 0.0})
    finetune(views, tmp_path / "resumed", tiny_model(), stopped)
    steps = [
        json.loads(line)["step"] for line in (tmp_path / "resumed" / "train_log.jsonl").read_text().splitlines()
    ]
    assert steps == [1]
    resumed = finetune(views, tmp_path / "resumed", tiny_model(seed=5), config)
    a, b = RelightDiffusion.load(straight).state_dict(), RelightDiffusion.load(resumed).state_dict()
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    assert sorted(p.name for p in (tmp_path / "resumed" / "checkpoints").iterdir()) == [
        "step_00000002",
        "step_00000003",
    ]
    assert json.loads((tmp_path / "resumed" / "selection.json").read_text())["images"]
    # The EMA is checkpointed as safetensors (no accelerate custom-object pickle) and resumes to the same state.
    checkpoints = tmp_path / "resumed" / "checkpoints"
    assert not list(checkpoints.rglob("custom_checkpoint_*"))
    straight_ema = load_safetensors(tmp_path / "straight" / "checkpoints" / "step_00000003" / EMA_FILE)
    resumed_ema = load_safetensors(checkpoints / "step_00000003" / EMA_FILE)
    assert straight_ema.keys() == resumed_ema.keys() and int(resumed_ema["num_updates"]) == 3
    assert all(torch.allclose(straight_ema[k], resumed_ema[k], atol=1e-6) for k in straight_ema)


def test_a_run_written_under_the_old_file_names_resumes_to_the_uninterrupted_weights(views, tmp_path):
    """Relighting runs before the fine-tunes shared one loop wrote ``train_config.json`` (without ``keep_checkpoints``
    and ``max_grad_norm``: it kept two checkpoints and clipped at norm 1) and ``log.jsonl``."""
    config = RelightTrainConfig(steps=3, batch_size=2, checkpoint_every=1, log_every=1, cycle_every=2)
    straight = finetune(views, tmp_path / "straight", tiny_model(), config, log=lambda _: None)
    old = tmp_path / "old"
    finetune(views, old, tiny_model(), RelightTrainConfig(**{**config.__dict__, "time_limit_s": 0.0}),
             log=lambda _: None)
    recorded = json.loads((old / "finetune_config.json").read_text())
    del recorded["keep_checkpoints"], recorded["max_grad_norm"]
    (old / "train_config.json").write_text(json.dumps(recorded))
    (old / "finetune_config.json").unlink()
    (old / "train_log.jsonl").rename(old / "log.jsonl")
    with pytest.raises(ValueError, match=r"train_config\.json: .*other settings \(max_grad_norm: 1\.0 -> 0\.5\)"):
        finetune(views, old, tiny_model(), RelightTrainConfig(**{**config.__dict__, "max_grad_norm": 0.5}))
    assert (old / "train_config.json").is_file() and not (old / "finetune_config.json").exists()  # left as it was
    messages = []
    resumed = finetune(views, old, tiny_model(seed=5), config, log=messages.append)
    assert any("resumed" in m and "step 1" in m for m in messages)
    assert any("log.jsonl renamed train_log.jsonl" in m for m in messages)
    a, b = RelightDiffusion.load(straight).state_dict(), RelightDiffusion.load(resumed).state_dict()
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    assert sorted(p.name for p in old.iterdir()) == ["checkpoints", "finetune_config.json", "model", "selection.json",
                                                     "train_log.jsonl"]
    records = [json.loads(line) for line in (old / "train_log.jsonl").read_text().splitlines()]
    assert [record["step"] for record in records] == [1, 2, 3]
    assert records[-1].keys() >= {"step", "loss", "lr", "seconds", "elapsed_s", "v_mse"}  # the novel-view log's keys
    assert json.loads((old / "finetune_config.json").read_text())["max_grad_norm"] == 1.0


def test_a_resume_with_other_settings_or_without_its_ema_is_refused(views, tmp_path):
    config = RelightTrainConfig(steps=2, batch_size=2, checkpoint_every=1, log_every=1, time_limit_s=0.0)
    finetune(views, tmp_path / "run", tiny_model(), config)
    recorded = json.loads((tmp_path / "run" / "finetune_config.json").read_text())
    for changed, message in (({"learning_rate": 1e-3}, r"learning_rate: 0\.0005 -> 0\.001"),
                             ({"steps": 3}, r"steps: 2 -> 3"),  # the cosine decay spans the steps
                             ({"batch_size": 3, "seed": 1}, r"batch_size: 2 -> 3; seed: 0 -> 1")):
        other = RelightTrainConfig(**{**config.__dict__, **changed})
        with pytest.raises(ValueError, match=rf"finetune_config\.json: .*other settings \({message}\)"):
            finetune(views, tmp_path / "run", tiny_model(), other)
    with pytest.raises(ValueError, match=r"other settings \(model\.use_source_light: False -> True\)"):
        finetune(views, tmp_path / "run", tiny_model(use_source_light=True), config)
    with pytest.raises(ValueError, match=r"other settings \(data_hash: '[0-9a-f]+' -> '[0-9a-f]+'\)"):
        finetune(load_relight_views([embedded_dataset("finetune/torus_jade")], resolution=16, min_lights=4),
                 tmp_path / "run", tiny_model(), config)
    assert json.loads((tmp_path / "run" / "finetune_config.json").read_text()) == recorded  # left as it was
    missing = tmp_path / "run" / "checkpoints" / "step_00000001" / EMA_FILE
    missing.unlink()
    with pytest.raises(DamagedFileError, match=f"{missing}: missing"):
        finetune(views, tmp_path / "run", tiny_model(), RelightTrainConfig(**{**config.__dict__, "time_limit_s": None}))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_seeded_finetune_on_cuda_repeats_to_the_bit(tmp_path):
    """Two relighting fine-tunes from one seed on CUDA, at 64 px (attention over 32 x 32 = 1,024 pixels, the cycle
    term included), end in the same weights, bit for bit."""
    views = load_relight_views([embedded_dataset("finetune/torus_jade")], resolution=64)
    config = RelightTrainConfig(steps=3, batch_size=2, checkpoint_every=100, log_every=100, cycle_every=2)
    first, second = (RelightDiffusion.load(finetune(views, tmp_path / name, tiny_model(resolution=64), config))
                     .state_dict() for name in ("first", "second"))
    initial = tiny_model(resolution=64).state_dict()
    assert any(not torch.equal(first[key].cpu(), initial[key].cpu()) for key in first), "the run changed no weight"
    different = [key for key in first if not torch.equal(first[key], second[key])]
    assert not different, f"{len(different)} of {len(first)} tensors differ between two seeded runs: {different[:5]}"


def test_lambertian_baseline_recovers_a_lambertian_image():
    from diamond_sss.data.conventions import intrinsics_from_fov
    from diamond_sss.diffusion.relight.baselines import lambertian_relight, lambertian_shading

    # A plane z = 0 seen from z = 3 (camera looks along -z in world: OpenCV w2c flips y and z).
    w2c = torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 3], [0, 0, 0, 1]])
    K = intrinsics_from_fov(0.6, 16, 16)
    depth = torch.full((16, 16, 1), 3.0)
    normals = torch.tensor([0.0, 0.0, 1.0]).expand(16, 16, 3)
    mask = torch.ones(16, 16, 1)
    lights = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.5, 1.5]])
    albedo = torch.tensor([0.8, 0.5, 0.2])
    images = [albedo * lambertian_shading(depth, normals, w2c, K, p) for p in lights]
    # Head-on light at distance 2 from the centre pixel: S = 1 / 4.
    assert float(lambertian_shading(depth, normals, w2c, K, lights[0])[8, 8, 0]) == pytest.approx(
        0.25, rel=0.02
    )
    relit = lambertian_relight(images[0], mask, depth, normals, w2c, K, lights[0], lights[1:])
    assert torch.allclose(relit[0], images[1].clamp(0, 1), atol=1e-5)
