"""Procedural closed triangle meshes for synthetic translucent objects.

Every shape is an implicit field ``f(p)`` (negative inside, positive outside, in scene units) turned into a
watertight mesh by marching tetrahedra on a regular grid, with outward vertex normals from the field's
gradient. Meshes are centred on their bounding-box centre and scaled so that ``max |v| = 1`` (they fit
the unit sphere). The world is Z-up. Only ``blob`` depends on the seed; all shapes are deterministic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Field = Callable[[np.ndarray], np.ndarray]

# Kuhn triangulation of the unit cube into 6 tetrahedra sharing the diagonal 0-6 (conforming between cubes).
_CUBE_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.int64
)
_CUBE_TETS = np.array(
    [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]], dtype=np.int64
)


@dataclass(frozen=True)
class TriangleMesh:
    """A closed triangle mesh: ``vertices [N,3]`` float32, ``faces [F,3]`` int32 (counter-clockwise seen
    from outside), ``normals [N,3]`` float32 outward unit vertex normals."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray


def smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth minimum ``-k log(exp(-a/k) + exp(-b/k))`` of two fields (blend radius ``k``, scene units)."""
    m = np.minimum(a, b)
    return m - k * np.log(np.exp(-(a - m) / k) + np.exp(-(b - m) / k))


def sphere_field(centre: tuple[float, float, float], radius: float) -> Field:
    """Signed distance to a sphere."""
    c = np.asarray(centre, dtype=np.float64)
    return lambda p: np.linalg.norm(p - c, axis=-1) - radius


def ellipsoid_field(centre: tuple[float, float, float], radii: tuple[float, float, float]) -> Field:
    """Approximate signed distance to an axis-aligned ellipsoid: ``(|(p - c) / r| - 1) min(r)``."""
    c = np.asarray(centre, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    return lambda p: (np.linalg.norm((p - c) / r, axis=-1) - 1.0) * r.min()


def capsule_field(a: tuple[float, float, float], b: tuple[float, float, float], radius: float) -> Field:
    """Signed distance to a capsule (segment ``a``-``b`` swept by a ball of ``radius``)."""
    pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    axis = pb - pa

    def field(p: np.ndarray) -> np.ndarray:
        t = np.clip(((p - pa) @ axis) / (axis @ axis), 0.0, 1.0)
        return np.linalg.norm(p - pa - t[..., None] * axis, axis=-1) - radius

    return field


def union_field(fields: list[Field], blend: float) -> Field:
    """Smooth union of several fields."""

    def field(p: np.ndarray) -> np.ndarray:
        out = fields[0](p)
        for other in fields[1:]:
            out = smooth_union(out, other(p), blend)
        return out

    return field


def torus_field(major: float, minor: float, tilt_deg: float) -> Field:
    """Signed distance to a torus around the Z axis, tilted by ``tilt_deg`` about X."""
    t = np.deg2rad(tilt_deg)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(t), np.sin(t)], [0.0, -np.sin(t), np.cos(t)]])

    def field(p: np.ndarray) -> np.ndarray:
        q = p @ rot.T
        ring = np.linalg.norm(q[..., :2], axis=-1) - major
        return np.sqrt(ring**2 + q[..., 2] ** 2) - minor

    return field


def blob_field(seed: int, amplitude: float = 0.12, waves: int = 6) -> Field:
    """Unit sphere with a smooth radial displacement ``r(d) = 1 + a/sqrt(K) sum_k sin(w_k . d + phi_k)``,
    random wave vectors ``|w_k| in [1.5, 3]`` and phases drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(waves, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    freqs = directions * rng.uniform(1.5, 3.0, size=(waves, 1))
    phases = rng.uniform(0.0, 2.0 * np.pi, size=waves)

    def field(p: np.ndarray) -> np.ndarray:
        r = np.linalg.norm(p, axis=-1)
        d = p / np.maximum(r, 1e-9)[..., None]
        radius = 1.0 + amplitude / np.sqrt(waves) * np.sin(d @ freqs.T + phases).sum(axis=-1)
        return (r - radius) * 0.8

    return field


def bunny_field() -> Field:
    """Bunny-like union of ellipsoids: body, head, two ears, tail (facing +X)."""
    parts = [
        ellipsoid_field((-0.1, 0.0, -0.25), (0.62, 0.45, 0.45)),
        ellipsoid_field((0.45, 0.0, 0.22), (0.3, 0.27, 0.28)),
        ellipsoid_field((0.38, 0.14, 0.7), (0.09, 0.065, 0.3)),
        ellipsoid_field((0.38, -0.14, 0.7), (0.09, 0.065, 0.3)),
        sphere_field((-0.72, 0.0, -0.1), 0.13),
    ]
    return union_field(parts, blend=0.06)


def bust_field() -> Field:
    """Bust: head, nose, neck (capsule) and shoulders (ellipsoid), facing +X."""
    parts = [
        ellipsoid_field((0.0, 0.0, 0.5), (0.3, 0.26, 0.36)),
        ellipsoid_field((0.29, 0.0, 0.45), (0.07, 0.05, 0.09)),
        capsule_field((0.0, 0.0, -0.05), (0.0, 0.0, 0.25), 0.13),
        ellipsoid_field((0.0, 0.0, -0.45), (0.32, 0.72, 0.3)),
    ]
    return union_field(parts, blend=0.08)


def trefoil_curve(t: np.ndarray) -> np.ndarray:
    """Trefoil knot ``c(t) = (sin t + 2 sin 2t, cos t - 2 cos 2t, -sin 3t)``, ``t in [0, 2 pi)`` -> ``[N,3]``
    (``max |c| = 3``; distinct strands stay more than 1.2 apart)."""
    return np.stack([np.sin(t) + 2.0 * np.sin(2.0 * t), np.cos(t) - 2.0 * np.cos(2.0 * t), -np.sin(3.0 * t)], axis=-1)


def knot_field(scale: float = 0.3, tube: float = 0.45, segments: int = 256) -> Field:
    """Signed distance to a trefoil-knot tube: ``min_k dist(p, segment_k) - scale tube``, the segments a closed
    polyline through ``scale c(2 pi k / segments)`` (:func:`trefoil_curve`); ``tube`` in curve units (< 0.6 keeps
    the strands apart)."""
    nodes = scale * trefoil_curve(np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False))
    starts, axes = nodes, np.roll(nodes, -1, axis=0) - nodes

    def field(p: np.ndarray) -> np.ndarray:
        nearest = np.full(p.shape[:-1], np.inf)
        for start, axis in zip(starts, axes, strict=True):
            t = np.clip(((p - start) @ axis) / (axis @ axis), 0.0, 1.0)
            nearest = np.minimum(nearest, np.linalg.norm(p - start - t[..., None] * axis, axis=-1))
        return nearest - scale * tube

    return field


def field_gradient(field: Field, points: np.ndarray, step: float = 1e-4) -> np.ndarray:
    """Central-difference gradient of ``field`` at ``points [N,3]`` -> ``[N,3]``."""
    grad = np.empty_like(points)
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = step
        grad[:, axis] = (field(points + offset) - field(points - offset)) / (2.0 * step)
    return grad


def marching_tetrahedra(field: Field, resolution: int, bound: float) -> TriangleMesh:
    """Zero level set of ``field`` on a ``resolution^3`` grid over ``[-bound, bound]^3``.

    Each cube is split into 6 tetrahedra; a tetrahedron with 1 or 3 inside corners emits one triangle,
    with 2 inside corners a quad (two triangles). Vertices on shared grid edges are welded, so the mesh
    is watertight when the surface stays inside the grid. Faces point outward by the tetrahedron's corner
    order: with corners ``(a, b, c, d)`` as emitted, a face keeps its order iff ``det(b - a, c - a, d - a) > 0``
    (on grid positions, never degenerate) and ``a`` is inside; sliver faces are oriented like their neighbours.
    """
    if resolution < 4:
        raise ValueError(f"resolution must be >= 4, got {resolution}")
    axis = np.linspace(-bound, bound, resolution)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    values = field(grid)
    values = np.where(values == 0.0, 1e-9, values)
    if (values.reshape(resolution, resolution, resolution)[[0, -1]] < 0).any():
        raise ValueError("the surface touches the grid boundary; increase bound")

    n = resolution
    cells = np.stack(np.meshgrid(*(np.arange(n - 1),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    corner_ids = cells[:, None, :] + _CUBE_CORNERS[None]
    corner_lin = (corner_ids[..., 0] * n + corner_ids[..., 1]) * n + corner_ids[..., 2]
    tets = corner_lin[:, _CUBE_TETS].reshape(-1, 4)
    inside = values[tets] < 0
    count = inside.sum(axis=1)
    tets, inside, count = (
        tets[(count > 0) & (count < 4)],
        inside[(count > 0) & (count < 4)],
        count[(count > 0) & (count < 4)],
    )
    # Order corners so that the odd one out (1 inside or 1 outside) comes first, or the inside pair first.
    key = np.where((count == 3)[:, None], ~inside, inside)
    order = np.argsort(~key, axis=1, kind="stable")
    t = np.take_along_axis(tets, order, axis=1)

    corners = grid[t]
    positive = np.linalg.det(corners[:, 1:] - corners[:, :1]) > 0
    # a (the first corner) is inside except when 3 corners are: then it is the one outside
    keep = positive == (count != 3)
    single = count != 2
    a, b, c, d = t[single].T
    tri_edges = [np.stack([np.stack([a, b], 1), np.stack([a, c], 1), np.stack([a, d], 1)], 1)]
    a, b, c, d = t[~single].T
    ac, ad, bd, bc = (np.stack(e, 1) for e in ((a, c), (a, d), (b, d), (b, c)))
    tri_edges += [np.stack([ac, ad, bd], 1), np.stack([ac, bd, bc], 1)]
    edges = np.concatenate(tri_edges, axis=0)  # [F, 3, 2] grid-vertex pairs
    keep = np.concatenate([keep[single], keep[~single], keep[~single]])

    edges = np.sort(edges, axis=-1)
    edge_keys = edges[..., 0] * (n**3) + edges[..., 1]
    unique_keys, faces = np.unique(edge_keys.reshape(-1), return_inverse=True)
    faces = faces.reshape(-1, 3)
    i0, i1 = unique_keys // (n**3), unique_keys % (n**3)
    v0, v1 = values[i0], values[i1]
    weight = (v0 / (v0 - v1))[:, None]
    vertices = grid[i0] + weight * (grid[i1] - grid[i0])

    faces[~keep] = faces[~keep][:, [0, 2, 1]]
    tri = vertices[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[area > 1e-14]

    normals = field_gradient(field, vertices)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return TriangleMesh(vertices.astype(np.float32), faces.astype(np.int32), normals.astype(np.float32))


def normalize_to_unit_sphere(mesh: TriangleMesh, radius: float = 1.0) -> TriangleMesh:
    """Centre on the bounding-box centre and scale uniformly so that ``max |v| = radius``."""
    v = mesh.vertices.astype(np.float64)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    v = v - centre
    v *= radius / np.linalg.norm(v, axis=1).max()
    return TriangleMesh(v.astype(np.float32), mesh.faces, mesh.normals)


def _sphere(seed: int) -> Field:
    return sphere_field((0.0, 0.0, 0.0), 0.9)


def _torus(seed: int) -> Field:
    return torus_field(0.7, 0.26, tilt_deg=30.0)


def _blob(seed: int) -> Field:
    return blob_field(seed)


def _bunny(seed: int) -> Field:
    return bunny_field()


def _bust(seed: int) -> Field:
    return bust_field()


def _knot(seed: int) -> Field:
    return knot_field()


SHAPES: dict[str, Callable[[int], Field]] = {
    "sphere": _sphere,
    "torus": _torus,
    "blob": _blob,
    "bunny": _bunny,
    "bust": _bust,
    "knot": _knot,
}


def shape_names() -> list[str]:
    """Names accepted by :func:`build_shape`."""
    return sorted(SHAPES)


def build_shape(name: str, seed: int = 0, resolution: int = 64) -> TriangleMesh:
    """The named procedural shape as a closed mesh fitting the unit sphere (``max |v| = 1``)."""
    if name not in SHAPES:
        raise ValueError(f"unknown shape {name!r}; valid shapes: {', '.join(shape_names())}")
    return normalize_to_unit_sphere(marching_tetrahedra(SHAPES[name](seed), resolution, bound=1.3))
