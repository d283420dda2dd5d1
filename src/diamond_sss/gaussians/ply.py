"""PLY export / import of a :class:`GaussianModel`, readable by common 3DGS splat viewers.

One ``vertex`` element, float32 properties, binary little-endian:

* standard 3DGS fields: ``x, y, z``, ``nx, ny, nz`` (here: the raw normals), ``f_dc_0..2``,
  ``f_rest_0..44`` (all 0), ``opacity`` (logit), ``scale_0..2`` (log), ``rot_0..3`` (``wxyz``, raw).
  The viewer colour comes from the base colour: ``f_dc = (c - 0.5) / C0`` with ``C0 = 0.28209479177387814``,
  so a viewer evaluating ``C0 f_dc + 0.5`` shows the (linear) base colour ``c``;
* DIAMOND-SSS fields, raw (pre-activation) values: ``base_color_0..2``, ``roughness``, ``metallic``,
  ``subsurface`` (logits) and ``vis_sh_0..15`` (SH coefficients).

:func:`import_ply` reads the raw fields back exactly; ``f_dc`` / ``f_rest`` are derived and ignored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from diamond_sss.gaussians.model import NUM_VISIBILITY_SH, SH_C0, GaussianModel
from diamond_sss.utils.io import atomic_write

NUM_F_REST = 45
"""Degree-3 colour SH of standard 3DGS files minus the DC band: 15 coefficients x 3 channels."""

_RAW_FIELDS: dict[str, list[str]] = {
    "means": ["x", "y", "z"],
    "normals": ["nx", "ny", "nz"],
    "opacities": ["opacity"],
    "scales": [f"scale_{i}" for i in range(3)],
    "quats": [f"rot_{i}" for i in range(4)],
    "base_color": [f"base_color_{i}" for i in range(3)],
    "roughness": ["roughness"],
    "metallic": ["metallic"],
    "subsurface": ["subsurface"],
    "visibility_sh": [f"vis_sh_{i}" for i in range(NUM_VISIBILITY_SH)],
}
"""Raw parameter -> its PLY property names."""

_PROPERTY_ORDER = (
    ["x", "y", "z", "nx", "ny", "nz"]
    + [f"f_dc_{i}" for i in range(3)]
    + [f"f_rest_{i}" for i in range(NUM_F_REST)]
    + ["opacity"]
    + _RAW_FIELDS["scales"]
    + _RAW_FIELDS["quats"]
    + _RAW_FIELDS["base_color"]
    + ["roughness", "metallic", "subsurface"]
    + _RAW_FIELDS["visibility_sh"]
)


def base_color_to_sh_dc(base_color: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH colour a 3DGS viewer decodes to ``base_color``: ``f_dc = (c - 0.5) / C0``."""
    return (base_color - 0.5) / SH_C0


def export_ply(model: GaussianModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` atomically (temporary file in the same folder, then ``os.replace``)."""
    path = Path(path)
    state = model.state_tensors()
    columns: dict[str, np.ndarray] = {}
    for key, names in _RAW_FIELDS.items():
        values = state[key].reshape(model.num_gaussians, -1).numpy().astype(np.float32)
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
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Gaussian PLY {path} does not exist")
    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise ValueError(f"Gaussian PLY {path} has no 'vertex' element")
    vertex = ply["vertex"]
    available = {prop.name for prop in vertex.properties}
    raw: dict[str, torch.Tensor] = {}
    for key, names in _RAW_FIELDS.items():
        for name in names:
            if name not in available:
                raise ValueError(f"Gaussian PLY {path}: vertex element has no property {name!r}")
        values = np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=-1)
        raw[key] = torch.from_numpy(values)
    raw["opacities"] = raw["opacities"][:, 0]
    return GaussianModel(raw, requires_grad=requires_grad)
