"""PLY files: export / import of a :class:`GaussianModel` (readable by common 3DGS splat viewers) and the
``points3d.ply`` point clouds of a data set (:func:`load_points3d_ply`), through one vertex reader.

Gaussians: one ``vertex`` element, float32 properties, binary little-endian:

* standard 3DGS fields: ``x, y, z``, ``nx, ny, nz`` (here: the raw normals), ``f_dc_0..2``,
  ``f_rest_0..44`` (all 0), ``opacity`` (logit), ``scale_0..2`` (log), ``rot_0..3`` (``wxyz``, raw).
  The viewer colour comes from the base colour: ``f_dc = (c - 0.5) / C0`` with ``C0 = 0.28209479177387814``,
  so a viewer evaluating ``C0 f_dc + 0.5`` shows the (linear) base colour ``c``;
* DIAMOND-SSS fields, raw (pre-activation) values: ``base_color_0..2``, ``roughness``, ``metallic``,
  ``subsurface`` (logits) and ``vis_sh_0..15`` (SH coefficients).

:func:`import_ply` reads the raw fields back exactly; ``f_dc`` / ``f_rest`` are derived and ignored.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError
from torch import Tensor

from diamond_sss.data.conventions import srgb_to_linear
from diamond_sss.errors import DamagedFileError
from diamond_sss.gaussians.model import GAUSSIAN_PARAMS, GaussianModel
from diamond_sss.shading.sh import SH_C0
from diamond_sss.utils.io import atomic_write

NUM_F_REST = 45
"""Degree-3 colour SH of standard 3DGS files minus the DC band: 15 coefficients x 3 channels."""

_RAW_FIELDS: dict[str, tuple[str, ...]] = {param.name: param.ply for param in GAUSSIAN_PARAMS}
"""Raw parameter -> its PLY property names."""

_LEADING = ("means", "normals")
"""Written before the derived viewer colour (``f_dc``, ``f_rest``), then ``opacities, scales, quats`` as in 3DGS
files, then the rest in storage order."""

_PROPERTY_ORDER = [
    *(name for key in _LEADING for name in _RAW_FIELDS[key]),
    *(f"f_dc_{i}" for i in range(3)),
    *(f"f_rest_{i}" for i in range(NUM_F_REST)),
    *(name for key in ("opacities", "scales", "quats") for name in _RAW_FIELDS[key]),
    *(name for param in GAUSSIAN_PARAMS if param.name not in (*_LEADING, "opacities", "scales", "quats")
      for name in param.ply),
]


def read_vertices(path: str | Path, label: str, required: Sequence[str]) -> tuple[PlyElement, set[str]]:
    """The ``vertex`` element of the PLY file ``path`` and its property names; errors name ``label``, the file
    and the first of ``required`` that is missing (a damaged file: :class:`DamagedFileError`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{label} {path} does not exist")
    try:
        ply = PlyData.read(str(path))
    except PlyParseError as exc:
        raise DamagedFileError(f"{path}: damaged or truncated {label} PLY file ({exc})") from exc
    if "vertex" not in ply:
        raise ValueError(f"{label} {path} has no 'vertex' element")
    vertex = ply["vertex"]
    names = {prop.name for prop in vertex.properties}
    for name in required:
        if name not in names:
            raise ValueError(f"{label} {path}: vertex element has no property {name!r}")
    return vertex, names


def load_points3d_ply(path: str | Path) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """Read a ``points3d.ply``: ``points [N,3]``, ``colors [N,3] | None``, ``normals [N,3] | None``.

    Needs a ``vertex`` element with ``x, y, z``. Colours (``red, green, blue``: 8-bit, 16-bit or
    float in ``[0,1]``) are sRGB on disk and returned linear (float32, ``[0,1]``). Normals
    (``nx, ny, nz``) are returned only when present and not all zero (many writers fill them with 0).
    """
    vertex, names = read_vertices(path, "point cloud", ("x", "y", "z"))

    def stack(keys: tuple[str, str, str]) -> np.ndarray:
        return np.stack([np.asarray(vertex[k]) for k in keys], axis=-1)

    points = torch.from_numpy(stack(("x", "y", "z")).astype(np.float32))
    colors = None
    color_keys = ("red", "green", "blue")
    present = [k for k in color_keys if k in names]
    if present and len(present) < 3:
        missing = sorted(set(color_keys) - set(present))
        raise ValueError(f"point cloud {path}: vertex element has {present} but no property {missing[0]!r}")
    if present:
        raw = stack(color_keys)
        if np.issubdtype(raw.dtype, np.integer):
            raw = raw.astype(np.float32) / float(np.iinfo(raw.dtype).max)
        colors = srgb_to_linear(torch.from_numpy(raw.astype(np.float32)))
    normals = None
    if all(k in names for k in ("nx", "ny", "nz")):
        raw_normals = torch.from_numpy(stack(("nx", "ny", "nz")).astype(np.float32))
        if raw_normals.abs().amax() > 0:
            normals = raw_normals
    if not torch.isfinite(points).all():
        raise ValueError(f"point cloud {path} has non-finite positions")
    return points, colors, normals


def base_color_to_sh_dc(base_color: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH colour a 3DGS viewer decodes to ``base_color``: ``f_dc = (c - 0.5) / C0``."""
    return (base_color - 0.5) / SH_C0


def export_ply(model: GaussianModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` atomically (temporary file in the same folder, then ``os.replace``)."""
    path = Path(path)
    state = model.state_tensors()
    columns: dict[str, np.ndarray] = {}
    for key, names in _RAW_FIELDS.items():
        values = state[key].reshape(model.num_gaussians, len(names)).numpy().astype(np.float32)
        for column, name in enumerate(names):
            columns[name] = values[:, column]
    f_dc = base_color_to_sh_dc(torch.sigmoid(state["base_color"])).numpy().astype(np.float32)
    for channel in range(3):
        columns[f"f_dc_{channel}"] = f_dc[:, channel]
    zeros = np.zeros(model.num_gaussians, dtype=np.float32)
    for index in range(NUM_F_REST):
        columns[f"f_rest_{index}"] = zeros

    vertices = np.empty(model.num_gaussians, dtype=[(name, "f4") for name in _PROPERTY_ORDER])
    for name in _PROPERTY_ORDER:
        vertices[name] = columns[name]
    ply = PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<")

    return atomic_write(path, lambda tmp: ply.write(str(tmp)))


def import_ply(path: str | Path, requires_grad: bool = True) -> GaussianModel:
    """Read a PLY written by :func:`export_ply` back into a :class:`GaussianModel` (bit-exact)."""
    stored = {name for names in _RAW_FIELDS.values() for name in names}
    vertex, _ = read_vertices(path, "Gaussian PLY", [name for name in _PROPERTY_ORDER if name in stored])
    raw: dict[str, torch.Tensor] = {}
    for key, names in _RAW_FIELDS.items():
        values = np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=-1)
        raw[key] = torch.from_numpy(values)
    raw["opacities"] = raw["opacities"][:, 0]
    return GaussianModel(raw, requires_grad=requires_grad)
