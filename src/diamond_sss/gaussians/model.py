"""Relightable Gaussians of the SSS-3DGS backbone (method.md §2).

Every per-Gaussian quantity is stored *raw* (unconstrained) in ``GaussianModel.params``, a
``torch.nn.ParameterDict`` whose layout is the one gsplat's densification strategies expect
(``means``, ``scales``, ``quats`` and ``opacities`` of shape ``[N]``; any further key is carried
along by ``gsplat.strategy.ops``). Activations are applied on access:

==================  ========  ===============================  =====================================
key                 shape     raw value                        activated property
==================  ========  ===============================  =====================================
``means``           ``[N,3]`` world position                   identity (scene units)
``scales``          ``[N,3]`` ``log s``                        ``exp`` (scene units, std. deviation)
``quats``           ``[N,4]`` quaternion ``wxyz``, any norm    unit quaternion
``opacities``       ``[N]``   ``logit o``                      ``sigmoid``
``normals``         ``[N,3]`` any non-zero vector              unit vector
``base_color``      ``[N,3]`` ``logit c``                      ``sigmoid`` (linear albedo)
``roughness``       ``[N,1]`` logit                            ``sigmoid``
``metallic``        ``[N,1]`` logit                            ``sigmoid``
``subsurface``      ``[N,1]`` logit                            ``sigmoid`` (subsurfaceness ``s``)
``visibility_sh``   ``[N,16]`` degree-3 SH coefficients        raw; ``v(w) = clamp(SH(w) + 0.5, 0, 1)``
==================  ========  ===============================  =====================================

There is no colour SH: all colour comes from shading.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor, nn

from diamond_sss.shading.sh import SH_C0
from diamond_sss.utils import rng

VISIBILITY_SH_DEGREE = 3
NUM_VISIBILITY_SH = (VISIBILITY_SH_DEGREE + 1) ** 2


@dataclass(frozen=True)
class GaussianParam:
    """One raw (pre-activation) per-Gaussian parameter: its per-Gaussian trailing ``shape``, its property names
    in a PLY file and the field of ``TrainConfig.lr`` holding its learning rate (``None``: the positions' own
    schedule)."""

    name: str
    shape: tuple[int, ...]
    ply: tuple[str, ...]
    lr: str | None


def _numbered(prefix: str, count: int) -> tuple[str, ...]:
    return tuple(f"{prefix}_{i}" for i in range(count))


GAUSSIAN_PARAMS: tuple[GaussianParam, ...] = (
    GaussianParam("means", (3,), ("x", "y", "z"), None),
    GaussianParam("scales", (3,), _numbered("scale", 3), "scaling"),
    GaussianParam("quats", (4,), _numbered("rot", 4), "rotation"),
    GaussianParam("opacities", (), ("opacity",), "opacity"),
    GaussianParam("normals", (3,), ("nx", "ny", "nz"), "normal"),
    GaussianParam("base_color", (3,), _numbered("base_color", 3), "base_color"),
    GaussianParam("roughness", (1,), ("roughness",), "roughness"),
    GaussianParam("metallic", (1,), ("metallic",), "metallic"),
    GaussianParam("subsurface", (1,), ("subsurface",), "subsurfacedness"),
    GaussianParam("visibility_sh", (NUM_VISIBILITY_SH,), _numbered("vis_sh", NUM_VISIBILITY_SH), "visibility"),
)
"""The raw parameters of a Gaussian, in storage order: the one list the shapes, the PLY fields and the
learning-rate keys are read from."""

PARAM_SHAPES: dict[str, tuple[int, ...]] = {param.name: param.shape for param in GAUSSIAN_PARAMS}
"""Per-Gaussian trailing shape of every raw parameter, in storage order."""

SCALE_NEIGHBOURS = 3
"""Neighbours whose RMS distance is a Gaussian's initial scale (:func:`nearest_neighbor_scales`): a point cloud
needs more points than this."""

_LOGIT_EPS = 1e-6
_MIN_KNN_DIST2 = 1e-7


def _logit(value: Tensor | float) -> Tensor:
    """``log(p / (1 - p))`` with ``p`` clamped to ``[1e-6, 1 - 1e-6]`` so that 0 and 1 stay finite."""
    return torch.logit(torch.as_tensor(value, dtype=torch.float32), eps=_LOGIT_EPS)


def nearest_neighbor_scales(points: Tensor, k: int = SCALE_NEIGHBOURS) -> Tensor:
    """Isotropic initial scale per point: RMS distance to its ``k`` nearest neighbours. ``[N,3] -> [N]``.

    ``s_i = sqrt(mean_j ||p_i - p_j||^2)`` over the ``k`` nearest ``j != i`` (3DGS / gsplat's
    ``simple_trainer``), squared distances clamped below at 1e-7. A k-d tree (``scipy.spatial.cKDTree``,
    float64, all cores) makes it ``O(N log N)``; the queries run in the tree's leaf order, which keeps
    them cache-local (one million points: ~2.5 s on two cores instead of ~8 s in input order).
    The result is float32 on the device of ``points``.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [N,3], got {tuple(points.shape)}")
    num_points = points.shape[0]
    if num_points <= k:
        raise ValueError(f"need more than k={k} points to estimate scales from neighbours, got {num_points}")
    cloud = points.detach().to("cpu", torch.float64).numpy()
    tree = cKDTree(cloud, balanced_tree=False, compact_nodes=False)
    order = torch.from_numpy(tree.indices.copy())  # scipy hands out a read-only view
    distances, _ = tree.query(cloud[tree.indices], k=k + 1, workers=-1)
    dist2 = torch.empty(num_points, dtype=torch.float64)
    dist2[order] = torch.from_numpy(distances[:, 1:]).square().mean(dim=1)
    return dist2.clamp_min(_MIN_KNN_DIST2).sqrt().to(device=points.device, dtype=torch.float32)


def outward_normals(points: Tensor) -> Tensor:
    """Unit vectors from the centroid of ``points`` to each point. ``[N,3] -> [N,3]``.

    A point at the centroid gets ``+Z``. A first guess for a closed, roughly star-shaped object.
    """
    offsets = points - points.mean(dim=0, keepdim=True)
    length = offsets.norm(dim=-1, keepdim=True)
    fallback = torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device).expand_as(offsets)
    return torch.where(length > 1e-12, offsets / length.clamp_min(1e-12), fallback)


class GaussianModel(nn.Module):
    """A set of relightable 3D Gaussians with raw parameters in ``self.params`` (see module docstring).

    Args:
        raw_params: one tensor per key of :data:`PARAM_SHAPES`, shaped ``[N, *PARAM_SHAPES[key]]``.
        requires_grad: whether the parameters are trainable.
    """

    def __init__(self, raw_params: Mapping[str, Tensor], requires_grad: bool = True) -> None:
        super().__init__()
        _validate_raw_params(raw_params)
        self.params = nn.ParameterDict(
            {
                name: nn.Parameter(raw_params[name].detach().clone().float(), requires_grad=requires_grad)
                for name in PARAM_SHAPES
            }
        )

    @classmethod
    def from_points(
        cls,
        points: Tensor,
        colors: Tensor | None = None,
        normals: Tensor | None = None,
        *,
        init_scale: float | None = None,
        init_opacity: float = 0.1,
        init_base_color: float = 0.5,
        init_roughness: float = 0.5,
        init_metallic: float = 0.05,
        init_subsurface: float = 0.5,
        init_visibility: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> GaussianModel:
        """One isotropic Gaussian per point.

        Args:
            points: ``[N,3]`` world positions.
            colors: ``[N,3]`` linear base colours in ``[0,1]``; ``None`` -> ``init_base_color`` everywhere.
            normals: ``[N,3]`` normals (normalised here); ``None`` -> outward from the centroid.
            init_scale: scale (std. deviation, scene units) of every Gaussian; ``None`` -> RMS distance to
                the 3 nearest neighbours per point (:func:`nearest_neighbor_scales`).
            init_opacity, init_roughness, init_metallic, init_subsurface: initial activated values in
                ``(0,1)``; stored as logits.
            init_visibility: initial constant visibility ``v`` in ``[0,1]``: the SH DC coefficient is
                ``(v - 0.5) / C0`` and all higher bands are zero, so ``v(w) = v`` in every direction.
            generator: source of the random initial orientations (uniform unit quaternions, as gsplat's
                trainer; irrelevant to the isotropic start but they break symmetry once scales diverge).
        """
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise ValueError(f"points must have shape [N,3] with N > 0, got {tuple(points.shape)}")
        points = points.detach().float()
        num, device = points.shape[0], points.device
        for name, value in [
            ("init_opacity", init_opacity),
            ("init_base_color", init_base_color),
            ("init_roughness", init_roughness),
            ("init_metallic", init_metallic),
            ("init_subsurface", init_subsurface),
        ]:
            if not 0.0 < value < 1.0:
                raise ValueError(f"{name} must lie in (0, 1), got {value}")
        if not 0.0 <= init_visibility <= 1.0:
            raise ValueError(f"init_visibility must lie in [0, 1], got {init_visibility}")

        if init_scale is None:
            if num <= SCALE_NEIGHBOURS:
                raise ValueError(f"init_scale=None needs at least {SCALE_NEIGHBOURS + 1} points for the "
                                 f"{SCALE_NEIGHBOURS}-NN estimate, got {num}")
            scales = nearest_neighbor_scales(points).unsqueeze(-1).expand(num, 3)
        else:
            if init_scale <= 0.0:
                raise ValueError(f"init_scale must be positive, got {init_scale}")
            scales = torch.full((num, 3), float(init_scale), device=device)

        if colors is None:
            base_color = torch.full((num, 3), init_base_color, device=device)
        else:
            if colors.shape != points.shape:
                raise ValueError(f"colors must have shape {tuple(points.shape)}, got {tuple(colors.shape)}")
            base_color = colors.detach().float().to(device)

        if normals is None:
            unit_normals = outward_normals(points)
        else:
            if normals.shape != points.shape:
                raise ValueError(f"normals must have shape {tuple(points.shape)}, got {tuple(normals.shape)}")
            unit_normals = F.normalize(normals.detach().float().to(device), dim=-1)

        quats = F.normalize(rng.randn(num, 4, generator=generator, device=device), dim=-1)

        visibility_sh = torch.zeros(num, NUM_VISIBILITY_SH, device=device)
        visibility_sh[:, 0] = (init_visibility - 0.5) / SH_C0

        def constant(value: float, width: int) -> Tensor:
            return _logit(value).to(device).expand(num, width).clone()

        raw = {
            "means": points,
            "scales": scales.log(),
            "quats": quats,
            "opacities": _logit(init_opacity).to(device).expand(num).clone(),
            "normals": unit_normals,
            "base_color": _logit(base_color),
            "roughness": constant(init_roughness, 1),
            "metallic": constant(init_metallic, 1),
            "subsurface": constant(init_subsurface, 1),
            "visibility_sh": visibility_sh,
        }
        return cls(raw)

    @classmethod
    def from_state_tensors(cls, tensors: Mapping[str, Tensor], requires_grad: bool = True) -> GaussianModel:
        """Inverse of :meth:`state_tensors`.

        E.g. ``GaussianModel.from_state_tensors(safetensors.torch.load_file(path))``.
        """
        return cls(tensors, requires_grad=requires_grad)

    def state_tensors(self) -> dict[str, Tensor]:
        """Raw parameters as detached, contiguous CPU copies keyed as in :data:`PARAM_SHAPES`.

        Ready for ``safetensors.torch.save_file``.
        """
        return {name: self.params[name].detach().cpu().clone().contiguous() for name in PARAM_SHAPES}

    @property
    def num_gaussians(self) -> int:
        return self.params["means"].shape[0]

    @property
    def means(self) -> Tensor:
        """``[N,3]`` world positions."""
        return self.params["means"]

    @property
    def scales(self) -> Tensor:
        """``[N,3]`` standard deviations along the Gaussian's axes, ``exp(raw)``."""
        return torch.exp(self.params["scales"])

    @property
    def quats(self) -> Tensor:
        """``[N,4]`` unit quaternions ``wxyz``."""
        return F.normalize(self.params["quats"], dim=-1)

    @property
    def opacities(self) -> Tensor:
        """``[N]`` opacities in ``(0,1)``."""
        return torch.sigmoid(self.params["opacities"])

    @property
    def normals(self) -> Tensor:
        """``[N,3]`` unit normals."""
        return F.normalize(self.params["normals"], dim=-1)

    @property
    def base_color(self) -> Tensor:
        """``[N,3]`` linear base colour (albedo) in ``(0,1)``."""
        return torch.sigmoid(self.params["base_color"])

    @property
    def roughness(self) -> Tensor:
        """``[N,1]`` GGX roughness ``r`` in ``(0,1)`` (the NDF uses ``a = r^2``)."""
        return torch.sigmoid(self.params["roughness"])

    @property
    def metallic(self) -> Tensor:
        """``[N,1]`` metalness in ``(0,1)``."""
        return torch.sigmoid(self.params["metallic"])

    @property
    def subsurface(self) -> Tensor:
        """``[N,1]`` subsurfaceness ``s`` in ``(0,1)``: ``L = (1 - s) L_pbr + s R``."""
        return torch.sigmoid(self.params["subsurface"])

    @property
    def visibility_sh(self) -> Tensor:
        """``[N,16]`` raw degree-3 SH coefficients of visibility; ``v(w) = clamp(SH(w) + 0.5, 0, 1)``."""
        return self.params["visibility_sh"]

    def extra_repr(self) -> str:
        return f"num_gaussians={self.num_gaussians}"


def _validate_raw_params(raw_params: Mapping[str, Tensor]) -> None:
    """Raise ``ValueError`` unless ``raw_params`` holds exactly the keys of :data:`PARAM_SHAPES`, with
    consistent shapes and finite floating-point values."""
    missing = [name for name in PARAM_SHAPES if name not in raw_params]
    unknown = [name for name in raw_params if name not in PARAM_SHAPES]
    if missing or unknown:
        raise ValueError(f"Gaussian parameters: missing keys {missing}, unknown keys {unknown}")
    num = raw_params["means"].shape[0] if raw_params["means"].ndim > 0 else -1
    for name, trailing in PARAM_SHAPES.items():
        tensor = raw_params[name]
        if tuple(tensor.shape) != (num, *trailing):
            raise ValueError(
                f"Gaussian parameter {name!r} must have shape {(num, *trailing)}, got {tuple(tensor.shape)}"
            )
        if not tensor.is_floating_point():
            raise ValueError(f"Gaussian parameter {name!r} must be floating point, got {tensor.dtype}")
        if not torch.isfinite(tensor).all():
            raise ValueError(f"Gaussian parameter {name!r} contains non-finite values")
