"""Relighting augmentations: mirrored lights in closed form, mirror equivariance of the hint, linear gains."""

from __future__ import annotations

import pytest
import torch

from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.diffusion.relight.augment import (
    RelightAugmentConfig,
    augment_batch,
    mirror_batch,
    mirror_code,
    permute_colors,
    scale_radiance,
)
from diamond_sss.diffusion.relight.conditioning import model_to_image
from diamond_sss.diffusion.relight.data import load_relight_views
from diamond_sss.diffusion.relight.hint import lambertian_hint
from diamond_sss.diffusion.relight.light import light_code


@pytest.fixture(scope="module")
def batch():
    views = load_relight_views([embedded_dataset("finetune/torus_jade")], resolution=16)
    return views.batch(torch.tensor([0, 1, 2, 0]), torch.tensor([0, 1, 2, 3]), torch.tensor([3, 2, 1, 0]))


def test_mirror_code_is_the_code_of_the_mirrored_light():
    positions = torch.randn(20, 3, generator=torch.Generator().manual_seed(1)) * 3.0
    w2c = torch.eye(4).expand(20, 4, 4)
    mirrored = positions * torch.tensor([-1.0, 1.0, 1.0])
    expected = light_code(mirrored, w2c, torch.zeros(3), 1.5)
    assert torch.allclose(mirror_code(light_code(positions, w2c, torch.zeros(3), 1.5)), expected, atol=1e-5)


def test_mirrored_pairs_give_the_mirrored_hint(batch):
    chosen = torch.tensor([True, False, True, True])
    mirrored = mirror_batch(batch, chosen)
    hint = lambertian_hint(batch["conditioning"], batch["target_code"], batch["source_code"], (1.0,), (0.2,))
    hint_of_mirrored = lambertian_hint(
        mirrored["conditioning"], mirrored["target_code"], mirrored["source_code"], (1.0,), (0.2,)
    )
    expected = torch.where(chosen[:, None, None, None], hint.flip(-1), hint)
    assert torch.allclose(hint_of_mirrored, expected, atol=1e-5)
    assert not torch.allclose(hint_of_mirrored, hint, atol=1e-3)
    twice = mirror_batch(mirrored, chosen)
    for key, value in batch.items():
        assert torch.allclose(twice[key], value, atol=1e-5), key


def test_gains_scale_source_target_and_hint_alike(batch):
    gains = torch.tensor([[0.5, 0.5, 0.5], [2.0, 1.5, 1.0], [1.0, 1.0, 1.0], [0.7, 0.9, 1.1]])
    scaled = scale_radiance(batch, gains)
    for key in ("source", "target"):
        expected = (model_to_image(batch[key]) * gains[:, None, None, :]).clamp(0.0, 1.0)
        assert torch.allclose(model_to_image(scaled[key]), expected, atol=1e-5)
    assert torch.equal(scaled["conditioning"][:, 3:], batch["conditioning"][:, 3:])
    source = model_to_image(batch["conditioning"][:, 0:3])
    unclamped = (source * gains[:, None, None, :] <= 1.0).all(dim=(1, 2, 3))
    assert int(unclamped.sum()) >= 2
    hint = model_to_image(lambertian_hint(batch["conditioning"], batch["target_code"], batch["source_code"]))
    hint_scaled = model_to_image(
        lambertian_hint(scaled["conditioning"], scaled["target_code"], scaled["source_code"])
    )
    expected = (hint * gains[:, None, None, :]).clamp(0.0, 1.0)
    assert torch.allclose(hint_scaled[unclamped], expected[unclamped], atol=1e-4)


def test_colour_permutation_permutes_source_target_and_hint_alike(batch):
    orders = torch.tensor([[2, 0, 1], [0, 1, 2], [1, 0, 2], [2, 1, 0]])
    permuted = permute_colors(batch, orders)
    for key in ("source", "target"):
        for b in range(4):
            assert torch.equal(permuted[key][b], batch[key][b, orders[b]])
    assert torch.equal(permuted["conditioning"][:, 3:], batch["conditioning"][:, 3:])
    hint = lambertian_hint(batch["conditioning"], batch["target_code"], batch["source_code"])
    hint_permuted = lambertian_hint(permuted["conditioning"], permuted["target_code"], permuted["source_code"])
    for b in range(4):
        assert torch.allclose(hint_permuted[b], hint[b, orders[b]], atol=1e-5)
    assert not torch.allclose(hint_permuted[0], hint[0], atol=1e-3)


def test_augmentation_is_seeded_and_can_be_switched_off(batch):
    config = RelightAugmentConfig()
    first = augment_batch(batch, config, torch.Generator().manual_seed(3))
    again = augment_batch(batch, config, torch.Generator().manual_seed(3))
    assert all(torch.equal(first[k], again[k]) for k in batch)
    assert not torch.equal(first["target"], batch["target"])
    off = augment_batch(batch, RelightAugmentConfig.off(), torch.Generator())
    assert all(torch.allclose(off[k], batch[k], atol=1e-5) for k in batch)
    with pytest.raises(ValueError, match="exposure and tint"):
        RelightAugmentConfig(exposure=-1.0)
