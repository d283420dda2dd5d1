from __future__ import annotations

import math

import pytest
import torch

from diamond_sss.rendering import quat_to_rotmat
from diamond_sss.shading import (
    gaussian_transmittance,
    ray_gaussian_max_response,
    raytraced_visibility,
)

IDENTITY_QUAT = torch.tensor([[1.0, 0.0, 0.0, 0.0]])


def isotropic(centres, sigma, opacities):
    centres = torch.as_tensor(centres, dtype=torch.float32).reshape(-1, 3)
    n = centres.shape[0]
    return (
        centres,
        IDENTITY_QUAT.expand(n, 4),
        torch.full((n, 3), sigma),
        torch.as_tensor(opacities).reshape(n),
    )


def along_x(offsets_y=(0.0,)):
    origins = torch.tensor([[-5.0, y, 0.0] for y in offsets_y])
    return origins, torch.tensor([[1.0, 0.0, 0.0]]).expand_as(origins)


def random_scene(num, seed, spread=1.0):
    gen = torch.Generator().manual_seed(seed)
    means = spread * (torch.rand(num, 3, generator=gen) - 0.5)
    quats = torch.randn(num, 4, generator=gen)
    scales = 0.02 + 0.1 * torch.rand(num, 3, generator=gen)
    opacities = torch.rand(num, generator=gen)
    return means, quats, scales, opacities


def test_ray_through_centre_gives_one_minus_opacity():
    origins, dirs = along_x([0.0, 0.1, 0.4])
    transmittance = gaussian_transmittance(origins, dirs, *isotropic([0, 0, 0], 0.1, [0.7]))
    # On the centre: q = 0; at 1 sigma: q = 1; at 4 sigma (beyond the 3 sigma cull): untouched.
    torch.testing.assert_close(transmittance, torch.tensor([0.3, 1 - 0.7 * math.exp(-0.5), 1.0]))


def test_two_gaussians_multiply_and_exclude_skips_one():
    gaussians = isotropic([[0, 0, 0], [2, 0.05, 0]], 0.1, [0.6, 0.5])
    origins, dirs = along_x([0.0, 0.0, 0.0])
    exclude = torch.tensor([-1, 0, 1])
    transmittance = gaussian_transmittance(origins, dirs, *gaussians, exclude=exclude)
    second = 1 - 0.5 * math.exp(-0.5 * 0.25)  # 0.5 sigma off its centre
    torch.testing.assert_close(transmittance, torch.tensor([0.4 * second, second, 0.4]))


def test_t_range_limits_which_gaussians_count():
    gaussians = isotropic([[0, 0, 0], [2, 0, 0]], 0.1, [0.6, 0.5])
    origins, dirs = along_x([0.0, 0.0, 0.0, 0.0])
    # Per-ray t_max: before both, between them (a light at x = 1), past both, scalar t_min past the first.
    t_max = torch.tensor([4.0, 6.0, 100.0, math.inf])
    transmittance = gaussian_transmittance(origins, dirs, *gaussians, t_max=t_max)
    torch.testing.assert_close(transmittance, torch.tensor([1.0, 0.4, 0.2, 0.2]))
    behind = gaussian_transmittance(origins[:1], dirs[:1], *gaussians, t_min=6.0)
    torch.testing.assert_close(behind, torch.tensor([0.5]))


def test_quat_to_rotmat():
    half = math.sqrt(0.5)
    rot = quat_to_rotmat(torch.tensor([[half, 0.0, 0.0, half], [2.0, 0.0, 0.0, 0.0]]))
    torch.testing.assert_close(rot[0], torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    torch.testing.assert_close(rot[1], torch.eye(3))
    random = quat_to_rotmat(torch.randn(16, 4, generator=torch.Generator().manual_seed(0)))
    torch.testing.assert_close(
        random @ random.transpose(-1, -2), torch.eye(3).expand(16, 3, 3), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(random), torch.ones(16), atol=1e-5, rtol=0)


def test_anisotropic_max_response_matches_brute_force_sampling():
    gen = torch.Generator().manual_seed(4)
    means, quats, scales, _ = random_scene(6, seed=5)
    scales = scales.double() * torch.tensor([1.0, 3.0, 0.3], dtype=torch.float64)
    rot = quat_to_rotmat(quats.double())
    precision = rot @ torch.diag_embed(scales.pow(-2)) @ rot.transpose(-1, -2)
    origins = (means.double() + 0.05 * torch.randn(6, 3, generator=gen, dtype=torch.float64)) - 2.0
    dirs = torch.nn.functional.normalize(
        means.double() - origins + 0.1 * torch.randn(6, 3, generator=gen), dim=-1
    )
    whiten = rot.transpose(-1, -2) / scales.unsqueeze(-1)
    t_star, q_min = ray_gaussian_max_response(origins, dirs, means.double(), whiten)

    t = torch.linspace(0.0, 6.0, 600_001, dtype=torch.float64)
    offsets = origins[:, None, :] + t[None, :, None] * dirs[:, None, :] - means.double()[:, None, :]
    q = torch.einsum("nti,nij,ntj->nt", offsets, precision, offsets)
    q_brute, idx = q.min(dim=1)
    torch.testing.assert_close(q_min, q_brute, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(t_star, t[idx], rtol=0, atol=2e-5)


def brute_force_transmittance(origins, dirs, means, quats, scales, opacities, t_max):
    """Dense float64 reference: explicit covariance, explicit segment-vs-sphere cull, all pairs."""
    o, d, mu = origins.double(), dirs.double(), means.double()
    rot = quat_to_rotmat(quats.double())
    precision = rot @ torch.diag_embed(scales.double().pow(-2)) @ rot.transpose(-1, -2)
    diff = o[:, None, :] - mu[None, :, :]  # [R, N, 3]
    a = torch.einsum("ri,nij,rj->rn", d, precision, d)
    b = torch.einsum("ri,nij,rnj->rn", d, precision, diff)
    c = torch.einsum("rni,nij,rnj->rn", diff, precision, diff)
    t_star, q_min = -b / a, c - b * b / a
    t_closest = -(diff * d[:, None, :]).sum(-1)
    perp = (diff + t_closest[..., None] * d[:, None, :]).norm(dim=-1)
    radius = 3.0 * scales.double().amax(-1)
    near = (perp <= radius) & (t_closest + radius >= 1e-4) & (t_closest - radius <= t_max[:, None])
    counted = near & (t_star >= 1e-4) & (t_star <= t_max[:, None])
    alpha = opacities.double() * torch.exp(-0.5 * q_min)
    return torch.where(counted, 1 - alpha, torch.ones_like(alpha)).prod(dim=1)


def test_matches_dense_reference_and_chunking_does_not_matter():
    gaussians = random_scene(300, seed=1)
    gen = torch.Generator().manual_seed(2)
    origins = 0.8 * (torch.rand(200, 3, generator=gen) - 0.5)
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen), dim=-1)
    t_max = torch.where(torch.arange(200) % 2 == 0, torch.tensor(0.4), torch.tensor(math.inf))
    whole = gaussian_transmittance(origins, dirs, *gaussians, t_max=t_max)
    chunked = gaussian_transmittance(origins, dirs, *gaussians, t_max=t_max, ray_chunk=7, gaussian_chunk=13)
    torch.testing.assert_close(chunked, whole, rtol=1e-5, atol=1e-6)
    reference = brute_force_transmittance(origins, dirs, *gaussians, t_max).float()
    torch.testing.assert_close(whole, reference, rtol=1e-4, atol=1e-5)
    assert (whole < 0.99).sum() > 50 and (whole > 0.01).sum() > 50  # the scene is neither empty nor opaque


def test_default_chunks_are_small_on_the_cpu_and_budgeted_on_cuda():
    from diamond_sss.shading.raytrace import CPU_CHUNKS, CUDA_CHUNK_PAIRS, transmittance_chunks

    assert transmittance_chunks(10**6, torch.device("cpu")) == CPU_CHUNKS
    cuda = torch.device("cuda")  # a device object needs no GPU
    assert transmittance_chunks(6000, cuda) == (6000, CUDA_CHUNK_PAIRS // 6000)
    assert transmittance_chunks(10**6, cuda) == (8192, CUDA_CHUNK_PAIRS // 8192)
    assert transmittance_chunks(1, cuda) == (1, CUDA_CHUNK_PAIRS)
    _, gaussians = transmittance_chunks(8192, cuda)
    assert math.ceil(300_000 / gaussians) * 3 == 111  # host syncs of a ray-traced step at 300k (882 with CPU_CHUNKS)


def test_raytraced_visibility_towards_light_and_samples():
    # A at the origin, an opaque-ish blocker B on the +x axis.
    gaussians = isotropic([[0, 0, 0], [1, 0, 0]], 0.1, [0.9, 0.8])
    far = raytraced_visibility(*gaussians, torch.tensor([3.0, 0.0, 0.0]))
    assert far.dirs.shape == (2, 1, 3) and far.visibility.shape == (2, 1)
    torch.testing.assert_close(far.dirs[:, 0], torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    torch.testing.assert_close(far.visibility[:, 0], torch.tensor([0.2, 1.0]))  # each skips itself
    between = raytraced_visibility(*gaussians, torch.tensor([[0.5, 0.0, 0.0], [-3.0, 0.0, 0.0]]))
    # B looks back at A: a light at x = 0.5 sits before A (not counted), one at x = -3 lies behind it.
    torch.testing.assert_close(between.visibility, torch.tensor([[1.0, 1.0], [1.0, 0.1]]))

    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    first = raytraced_visibility(
        *gaussians, num_samples=64, generator=torch.Generator().manual_seed(0), normals=normals
    )
    again = raytraced_visibility(
        *gaussians, num_samples=64, generator=torch.Generator().manual_seed(0), normals=normals
    )
    assert first.dirs.shape == (2, 64, 3)
    torch.testing.assert_close(first.dirs, again.dirs)
    torch.testing.assert_close(first.dirs.norm(dim=-1), torch.ones(2, 64))
    assert torch.all((first.dirs * normals[:, None]).sum(-1) >= 0)
    # Sampled rays that pass within 0.1 of the other Gaussian's centre are the only ones shadowed.
    to_other = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    perp = (to_other[:, None] - (first.dirs * to_other[:, None]).sum(-1, keepdim=True) * first.dirs).norm(
        dim=-1
    )
    ahead = (first.dirs * to_other[:, None]).sum(-1) > 0
    clear = (perp > 0.3) | ~ahead
    assert torch.all(first.visibility[clear] == 1.0)
    with pytest.raises(ValueError, match="light_pos"):
        raytraced_visibility(*gaussians)


def test_bad_shapes_are_rejected():
    gaussians = isotropic([0, 0, 0], 0.1, [0.5])
    origins, dirs = along_x()
    with pytest.raises(ValueError, match="origins and dirs"):
        gaussian_transmittance(origins[0], dirs, *gaussians)
    with pytest.raises(ValueError, match="opacities"):
        gaussian_transmittance(origins, dirs, *gaussians[:3], torch.ones(1, 1))
    with pytest.raises(ValueError, match="t_min / t_max"):
        gaussian_transmittance(origins, dirs, *gaussians, t_max=torch.ones(3))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_cpu():
    gaussians = random_scene(500, seed=3)
    gen = torch.Generator().manual_seed(4)
    origins = 0.8 * (torch.rand(400, 3, generator=gen) - 0.5)
    dirs = torch.nn.functional.normalize(torch.randn(400, 3, generator=gen), dim=-1)
    cpu = gaussian_transmittance(origins, dirs, *gaussians)
    gpu = gaussian_transmittance(origins.cuda(), dirs.cuda(), *(g.cuda() for g in gaussians))
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-5)


def test_raytraced_visibility_from_a_subset_of_sources():
    generator = torch.Generator().manual_seed(0)
    means = torch.randn(40, 3, generator=generator)
    quats = torch.nn.functional.normalize(torch.randn(40, 4, generator=generator), dim=-1)
    scales = torch.rand(40, 3, generator=generator) * 0.3 + 0.05
    opacities = torch.rand(40, generator=generator)
    light = torch.tensor([3.0, 0.0, 0.0])
    full = raytraced_visibility(means, quats, scales, opacities, light)
    subset = torch.tensor([3, 17, 29])
    part = raytraced_visibility(means, quats, scales, opacities, light, sources=subset)
    assert part.visibility.shape == (3, 1)
    torch.testing.assert_close(part.visibility, full.visibility[subset])
    torch.testing.assert_close(part.dirs, full.dirs[subset])
