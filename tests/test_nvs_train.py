"""Novel-view fine-tuning: fixed-light sequences, a step that overfits one sample, exact resume."""

from __future__ import annotations

import json

import pytest
import torch
from tiny_models import TINY_NVS

from diamond_sss.data.analytic import make_capture
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.common.ema import EMA_FILE
from diamond_sss.diffusion.nvs.data import fixed_light_sequences, sample_batch
from diamond_sss.diffusion.nvs.model import NVSBatch, NVSConfig, NVSModel
from diamond_sss.diffusion.nvs.train import FinetuneConfig, finetune
from diamond_sss.errors import DamagedFileError
from diamond_sss.utils.io import load_safetensors

TINY = {**TINY_NVS, "warp_hint": False}
"""The base model (no warp hint); the hint is tested in test_nvs_warp.py."""


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    roots = []
    for i in range(2):
        root = tmp_path_factory.mktemp(f"object{i}")
        make_capture(root, views=5, lights=2, size=16)
        roots.append(root)
    return roots


def test_sequences_hold_one_light_each_and_batches_use_distinct_objects(objects):
    sequences = fixed_light_sequences(objects, size=8)
    assert len(sequences) == 4 and {len(s.views) for s in sequences} == {5}
    assert sequences[0].images.shape == (5, 4, 8, 8) and sequences[0].K[0, 0, 2] == pytest.approx(4.0)
    batch = sample_batch(sequences, 2, 3, torch.Generator().manual_seed(0))
    assert batch.targets.shape == (2, 3, 4, 8, 8) and batch.target_w2c.shape == (2, 3, 4, 4)
    # the reference is never among its own targets
    for o in range(2):
        assert not any(torch.equal(batch.reference_w2c[o], w) for w in batch.target_w2c[o])


@pytest.mark.parametrize("prediction_type", ["epsilon", "v_prediction"])
def test_training_steps_overfit_one_sample(objects, prediction_type):
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY, condition_dropout=0.0, prediction_type=prediction_type))
    batch = sample_batch(fixed_light_sequences(objects[:1], size=16), 1, 2, torch.Generator().manual_seed(1))
    optimizer = torch.optim.Adam(model.trainable_parameters(), lr=2e-3)
    losses = []
    for _ in range(40):
        loss = model.training_loss(
            batch, generator=torch.Generator().manual_seed(7)
        )  # same noise and timestep
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.2 * losses[0]


def test_all_views_of_an_object_share_one_timestep(objects):
    from diamond_sss.diffusion.common.schedulers import make_ddpm_scheduler

    model = NVSModel(NVSConfig(**TINY))
    scheduler = make_ddpm_scheduler(model.config.scheduler)
    seen = []
    add_noise = scheduler.add_noise

    def spy(clean, noise, timesteps):
        seen.append(timesteps.clone())
        return add_noise(clean, noise, timesteps)

    scheduler.add_noise = spy
    batch = sample_batch(fixed_light_sequences(objects, size=16), 2, 3, torch.Generator().manual_seed(1))
    model.training_loss(batch, generator=torch.Generator().manual_seed(4), scheduler=scheduler)
    per_object = seen[0].reshape(2, 3)
    assert (per_object == per_object[:, :1]).all()
    assert per_object[0, 0] != per_object[1, 0]


def test_gradient_checkpointing_gives_the_same_gradients(objects):
    torch.manual_seed(0)
    model = NVSModel(NVSConfig(**TINY))
    batch = sample_batch(fixed_light_sequences(objects[:1], size=16), 1, 2, torch.Generator().manual_seed(1))
    grads = []
    for enabled in (False, True):
        model.enable_gradient_checkpointing(enabled)
        model.zero_grad()
        model.training_loss(batch, generator=torch.Generator().manual_seed(3)).backward()
        grads.append(
            torch.cat([p.grad.flatten() for p in model.trainable_parameters() if p.grad is not None])
        )
    torch.testing.assert_close(grads[0], grads[1])


def tiny_finetune(**settings) -> FinetuneConfig:
    """A fine-tune of the tiny base model on two objects x two views per step."""
    return FinetuneConfig(**{"objects_per_batch": 2, "views_per_object": 2, "model": NVSConfig(**TINY), **settings})


def test_finetune_resumes_exactly_and_writes_a_loadable_model(objects, tmp_path):
    config = tiny_finetune(steps=4, warmup_steps=2, checkpoint_every=2, log_every=1)
    straight = finetune(objects, tmp_path / "straight", config, log=lambda _: None)
    config.steps = 2
    finetune(objects, tmp_path / "resumed", config, log=lambda _: None)
    config.steps = 4
    messages = []
    resumed = finetune(objects, tmp_path / "resumed", config, log=messages.append)
    assert any("resumed" in m and "step 2" in m for m in messages)
    a, b = load_safetensors(straight / "model.safetensors"), load_safetensors(resumed / "model.safetensors")
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], atol=1e-6, rtol=0, msg=key)
    assert sorted(p.name for p in (tmp_path / "resumed" / "checkpoints").iterdir()) == [
        "step_00000002",
        "step_00000004",
    ]
    NVSModel.load(resumed)
    # The EMA is checkpointed as safetensors (no accelerate custom-object pickle) and resumes to the same state.
    checkpoints = tmp_path / "resumed" / "checkpoints"
    assert not list(checkpoints.rglob("custom_checkpoint_*"))
    straight_ema = load_safetensors(tmp_path / "straight" / "checkpoints" / "step_00000004" / EMA_FILE)
    resumed_ema = load_safetensors(checkpoints / "step_00000004" / EMA_FILE)
    assert straight_ema.keys() == resumed_ema.keys() and int(resumed_ema["num_updates"]) == 4
    for key in straight_ema:
        torch.testing.assert_close(straight_ema[key], resumed_ema[key], atol=1e-6, rtol=0, msg=key)


def test_a_checkpoint_without_its_ema_is_a_damaged_file(objects, tmp_path):
    config = tiny_finetune(steps=1, warmup_steps=1, checkpoint_every=1, log_every=1)
    finetune(objects, tmp_path / "run", config, log=lambda _: None)
    missing = tmp_path / "run" / "checkpoints" / "step_00000001" / EMA_FILE
    missing.unlink()
    config.steps = 2
    with pytest.raises(DamagedFileError, match=f"{missing}: missing"):
        finetune(objects, tmp_path / "run", config, log=lambda _: None)


def test_a_resume_with_other_settings_or_data_is_refused_naming_them(objects, tmp_path):
    config = tiny_finetune(steps=1, warmup_steps=1, checkpoint_every=1, log_every=1)
    finetune(objects, tmp_path / "run", config, log=lambda _: None)
    recorded = json.loads((tmp_path / "run" / "finetune_config.json").read_text())
    for changed, message in (({"seed": 3, "learning_rate": 2e-4}, r"learning_rate: 0\.0001 -> 0\.0002; seed: 0 -> 3"),
                             ({"model": NVSConfig(**{**TINY, "prediction_type": "v_prediction"})},
                              r"model\.prediction_type: 'epsilon' -> 'v_prediction'")):
        other = tiny_finetune(steps=2, warmup_steps=1, checkpoint_every=1, log_every=1, **changed)
        with pytest.raises(ValueError, match=rf"finetune_config\.json: .*other settings \({message}\)"):
            finetune(objects, tmp_path / "run", other, log=lambda _: None)
    with pytest.raises(ValueError, match=r"other settings \(data_hash: '[0-9a-f]+' -> '[0-9a-f]+'\)"):
        finetune(objects[:1], tmp_path / "run", config, log=lambda _: None)
    assert json.loads((tmp_path / "run" / "finetune_config.json").read_text()) == recorded  # left as it was
    # its length, logging and checkpointing may change
    longer = tiny_finetune(steps=2, warmup_steps=1, checkpoint_every=2, log_every=2, time_limit_s=60.0)
    messages = []
    finetune(objects, tmp_path / "run", longer, log=messages.append)
    assert any("resumed" in m and "step 1" in m for m in messages)


def test_a_run_recorded_before_gradient_clipping_was_a_setting_resumes_unclipped(objects, tmp_path):
    """The fine-tunes' common folder (``diffusion/common/finetune.py``); a record without ``max_grad_norm`` stands
    for no clipping, as the novel-view fine-tune trained before the setting existed."""
    config = tiny_finetune(steps=1, warmup_steps=1, checkpoint_every=1, log_every=1)
    finetune(objects, tmp_path / "run", config, log=lambda _: None)
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["checkpoints", "finetune_config.json", "model",
                                                                    "train_log.jsonl"]
    record = json.loads((tmp_path / "run" / "train_log.jsonl").read_text())
    assert record.keys() == {"step", "loss", "lr", "seconds", "elapsed_s"} and record["step"] == 1
    settings = tmp_path / "run" / "finetune_config.json"
    settings.write_text(json.dumps({k: v for k, v in json.loads(settings.read_text()).items() if k != "max_grad_norm"}))
    clipped = tiny_finetune(steps=2, warmup_steps=1, checkpoint_every=1, log_every=1, max_grad_norm=1.0)
    with pytest.raises(ValueError, match=r"other settings \(max_grad_norm: None -> 1\.0\)"):
        finetune(objects, tmp_path / "run", clipped, log=lambda _: None)
    messages = []
    finetune(objects, tmp_path / "run", tiny_finetune(steps=2, warmup_steps=1, checkpoint_every=1, log_every=1),
             log=messages.append)
    assert any("resumed" in m and "step 1" in m for m in messages)
    assert json.loads(settings.read_text())["max_grad_norm"] is None


def test_a_time_limited_run_stops_checkpointed_and_resumes_to_the_uninterrupted_weights(objects, tmp_path):
    config = tiny_finetune(steps=3, warmup_steps=1, checkpoint_every=100, log_every=100)
    straight = finetune(objects, tmp_path / "straight", config, log=lambda _: None)
    boxed = tiny_finetune(steps=3, warmup_steps=1, checkpoint_every=100, log_every=100, time_limit_s=0.0)
    messages = []
    stopped = finetune(objects, tmp_path / "boxed", boxed, log=messages.append)
    assert any("time limit" in m and "step 1" in m for m in messages)
    assert [p.name for p in (tmp_path / "boxed" / "checkpoints").iterdir()] == ["step_00000001"]
    assert (tmp_path / "boxed" / "train_log.jsonl").read_text().count("\n") == 1
    NVSModel.load(stopped)
    resumed = finetune(objects, tmp_path / "boxed", config, log=lambda _: None)
    a, b = load_safetensors(straight / "model.safetensors"), load_safetensors(resumed / "model.safetensors")
    for key in a:
        torch.testing.assert_close(a[key], b[key], atol=1e-6, rtol=0, msg=key)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_seeded_finetune_on_cuda_repeats_to_the_bit(tmp_path):
    """The GPU prior's kind of run (warp hint with its residual, attention over 32 x 32 = 1,024 pixels, where fused
    attention kernels may split their backward pass across thread blocks) trained twice from one seed on CUDA
    ends in the same weights, bit for bit: the fine-tune's deterministic kernels cover every operator it runs."""
    objects = [embedded_dataset(f"finetune/{name}") for name in ("torus_jade", "blob_soap")]
    config = FinetuneConfig(objects_per_batch=2, views_per_object=2, steps=3, warmup_steps=1, checkpoint_every=100,
                            log_every=100, model=NVSConfig(**{**TINY_NVS, "image_size": 64, "hint_residual": True}))
    first, second = (load_safetensors(finetune(objects, tmp_path / name, config, log=lambda _: None)
                                      / "model.safetensors") for name in ("first", "second"))
    torch.manual_seed(config.seed)  # the fine-tune's initial weights
    initial = NVSModel(config.model).state_dict()
    assert any(not torch.equal(first[key].cpu(), initial[key]) for key in first), "the run changed no weight"
    different = [key for key in first if not torch.equal(first[key], second[key])]
    assert not different, f"{len(different)} of {len(first)} tensors differ between two seeded runs: {different[:5]}"


def test_a_run_starts_from_a_saved_models_weights_and_refuses_another_architecture(objects, tmp_path):
    torch.manual_seed(5)
    start = NVSModel(NVSConfig(**TINY)).save(tmp_path / "start")
    untrained = finetune(objects, tmp_path / "run", tiny_finetune(steps=0, init_from=str(start)), log=lambda _: None)
    a, b = load_safetensors(start / "model.safetensors"), load_safetensors(untrained / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    trained = finetune(objects, tmp_path / "trained", tiny_finetune(steps=2, warmup_steps=1, init_from=str(start)),
                       log=lambda _: None)
    moved = load_safetensors(trained / "model.safetensors")
    assert any(not torch.equal(a[k], moved[k]) for k in a)  # then it trains from there
    other = tiny_finetune(steps=1, init_from=str(start))
    other.model = NVSConfig(**{**TINY, "layers_per_block": 2})
    with pytest.raises(ValueError, match=r"config\.json: another architecture.*layers_per_block 2 here, 1 there"):
        finetune(objects, tmp_path / "other", other, log=lambda _: None)
    assert not (tmp_path / "other").exists()


def test_bf16_autocast_trains_near_the_float32_run(objects, tmp_path):
    losses = {}
    for precision in ("no", "bf16"):
        config = tiny_finetune(steps=1, warmup_steps=1, log_every=1, mixed_precision=precision)
        finetune(objects, tmp_path / precision, config, log=lambda _: None)
        losses[precision] = json.loads((tmp_path / precision / "train_log.jsonl").read_text())["loss"]
    assert losses["bf16"] != losses["no"]  # the forward pass ran in bfloat16
    assert losses["bf16"] == pytest.approx(losses["no"], rel=0.05)


def test_unknown_or_unavailable_precisions_are_refused(objects, tmp_path):
    with pytest.raises(ValueError, match="mixed_precision must be one of"):
        finetune(objects, tmp_path / "run", tiny_finetune(steps=1, mixed_precision="fp32"), log=lambda _: None)
    assert not (tmp_path / "run").exists()
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="'fp16' needs a CUDA GPU"):
            finetune(objects, tmp_path / "run", tiny_finetune(steps=1, mixed_precision="fp16"), log=lambda _: None)


def test_a_training_step_has_no_data_dependent_shapes():
    """On the meta device (shapes, no data) the whole loss and its backward pass run: no boolean-mask indexing,
    nonzero or item() in the step, each of which would make the host wait for the GPU on CUDA."""
    config = NVSConfig(**{**TINY_NVS, "hint_residual": True})
    model = NVSModel(config).to("meta")
    b, v, side = 2, 3, config.warp_source_size
    eye4, eye3 = torch.eye(4, device="meta"), torch.eye(3, device="meta")
    batch = NVSBatch(reference=torch.empty(b, 4, side, side, device="meta"), reference_w2c=eye4.expand(b, 4, 4),
                     target_w2c=eye4.expand(b, v, 4, 4), target_K=eye3.expand(b, v, 3, 3),
                     targets=torch.empty(b, v, 4, side, side, device="meta"), reference_K=eye3.expand(b, 3, 3),
                     reference_depth=torch.empty(b, 1, side, side, device="meta"))
    loss = model.training_loss(batch)
    loss.backward()
    assert loss.device.type == "meta" and loss.shape == ()

