"""Capture regimes (supplement Sec. B): which views, lights and images of a capture are used.

Spec strings:
    ``all``                   every observation;
    ``all-views-1-light``     every view under one light, lights spread evenly over the views;
    ``views=5%,lights=5%``    fractions of the lattice's views and lights (``max(1, round(p N))`` each),
                              and every captured image among them; counts (``views=5,lights=6``) and
                              ``all`` work on either side;
    ``images=10``             that many images, spread jointly over view and light directions.

A count larger than what the capture has is an error naming both numbers, never a silent cap.

Views and lights are picked by farthest-point sampling on their unit directions from the scene centre,
started from a seeded random choice; only observations that exist are used. On an incomplete lattice (each view
lit by some of the lights only) ``views=V,lights=L`` keeps those picks when all ``V x L`` images were captured;
otherwise it picks views and lights captured together (:func:`captured_together`), and when fewer than ``V x L``
images exist among any it finds, ``RegimeSelection.note`` says how many and why.
"""

from __future__ import annotations

import logging
import re
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from diamond_sss.data.dataset import OLATDataset, directions_from

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RegimeSelection:
    """The outcome of a regime: lattice view and light indices and the chosen observation indices; ``note`` says why
    fewer images than asked were selected (``None`` when there is nothing to say)."""

    spec: str
    seed: int
    views: list[int]
    lights: list[int]
    observations: list[int]
    note: str | None = None

    def to_json(self) -> dict:
        return {**asdict(self), "images": len(self.observations)}


def farthest_point_order(directions: Tensor, count: int, generator: torch.Generator) -> list[int]:
    """Greedy farthest-point sampling of ``count`` rows of unit vectors ``[N,3]``.

    Starts at a random row drawn from ``generator``; each next pick maximises the smallest Euclidean
    distance (monotone in angle on the unit sphere) to those already picked. Ties go to the lowest index.
    """
    total = directions.shape[0]
    count = min(count, total)
    if count <= 0:
        return []
    first = int(torch.randint(total, (1,), generator=generator))
    chosen = [first]
    nearest = (directions - directions[first]).norm(dim=-1)
    for _ in range(count - 1):
        nearest[chosen] = -1.0
        pick = int(torch.argmax(nearest))
        chosen.append(pick)
        nearest = torch.minimum(nearest, (directions - directions[pick]).norm(dim=-1))
    return chosen


def nearest_angle_deg(query: Tensor, reference: Tensor) -> Tensor:
    """Angle in degrees from each unit direction of ``query [N,3]`` to the nearest of ``reference [M,3]`` ``[N]``:
    e.g. how far a novel light lies from the lights a run was trained on."""
    cosine = (query @ reference.T).amax(dim=1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cosine))


def resolve_count(value: str, total: int, key: str) -> int:
    """``"5%"`` -> ``max(1, round(0.05 total))``; ``"7"`` -> 7; ``"all"`` -> ``total``.

    A count above ``total`` raises ``ValueError`` naming both numbers ("views=500 asks for 500 views; the capture
    has 40")."""
    value = value.strip()
    if value == "all":
        return total
    if value.endswith("%"):
        try:
            fraction = float(value[:-1]) / 100.0
        except ValueError as exc:
            raise ValueError(f"regime: '{key}={value}' is not a percentage") from exc
        if not 0.0 < fraction <= 1.0:
            raise ValueError(f"regime: '{key}={value}' must be in (0%, 100%]")
        return max(1, round(fraction * total))
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"regime: '{key}={value}' must be a positive count, a percentage or 'all'")
    if int(value) > total:
        raise ValueError(f"regime: '{key}={value}' asks for {int(value)} {key}; the capture has {total}")
    return int(value)


def select_regime(dataset: OLATDataset, spec: str, seed: int = 0) -> RegimeSelection:
    """Apply a regime spec to a dataset (see the module docstring). Deterministic in ``(spec, seed)``."""
    spec = spec.strip()
    generator = torch.Generator().manual_seed(seed)
    present = dataset.presence
    center = dataset.bounds.center
    view_dirs = directions_from(dataset.camera_centers, center)
    light_dirs = directions_from(dataset.light_positions, center)
    captured_views = torch.nonzero(present.any(1)).flatten()
    captured_lights = torch.nonzero(present.any(0)).flatten()

    if spec == "all":
        return _from_observations(dataset, spec, seed, range(len(dataset.observations)))
    if spec == "all-views-1-light":
        view_order = [int(captured_views[i]) for i in farthest_point_order(view_dirs[captured_views],
                                                                            len(captured_views), generator)]
        light_order = [int(captured_lights[i]) for i in farthest_point_order(light_dirs[captured_lights],
                                                                              len(captured_lights), generator)]
        chosen = []
        for rank, view in enumerate(view_order):
            rotated = light_order[rank % len(light_order):] + light_order[: rank % len(light_order)]
            light = next(light for light in rotated if present[view, light])
            chosen.append(dataset.observation_index(view, light))
        return _from_observations(dataset, spec, seed, chosen)
    match = re.fullmatch(r"images=(\d+)", spec)
    if match:
        return _select_images(dataset, spec, seed, int(match.group(1)), view_dirs, light_dirs, generator)
    parts = dict(_key_value(part, spec) for part in spec.split(","))
    if set(parts) != {"views", "lights"}:
        raise ValueError(f"regime '{spec}': expected 'all', 'all-views-1-light', 'images=N' or "
                         f"'views=X,lights=Y' (X, Y: a percentage like 5%, a count, or all)")
    num_views = resolve_count(parts["views"], len(captured_views), "views")
    num_lights = resolve_count(parts["lights"], len(captured_lights), "lights")
    views = [int(captured_views[i]) for i in farthest_point_order(view_dirs[captured_views], num_views, generator)]
    lights = [int(captured_lights[i]) for i in farthest_point_order(light_dirs[captured_lights], num_lights,
                                                                     generator)]
    note = None
    if not bool(present[views][:, lights].all()):
        views, lights = captured_together(present, lights, num_views, view_dirs, light_dirs, generator)
        found = int(present[views][:, lights].sum())
        if found < num_views * num_lights:
            note = (f"{found} of {num_views} x {num_lights} = {num_views * num_lights} images: the search found no "
                    f"{num_views} views imaged under the same {num_lights} lights in {dataset.json_path} (an "
                    "incomplete lattice); these views and lights share the most captured images it found")
            logger.warning("regime '%s' (seed %d) selects %s", spec, seed, note)
    light_set = set(lights)
    view_set = set(views)
    chosen = [i for i, obs in enumerate(dataset.observations) if obs.view in view_set and obs.light in light_set]
    return RegimeSelection(spec=spec, seed=seed, views=sorted(views), lights=sorted(lights), observations=chosen,
                           note=note)


def most_covered(coverage: Tensor, directions: Tensor, count: int, generator: torch.Generator) -> list[int]:
    """``count`` rows with the largest ``coverage [N]`` (captured images among the other kind's picks), spread by
    farthest-point sampling on ``directions [N,3]`` among equal coverage: each pick takes the highest coverage left,
    then the largest smallest distance to the rows already picked (the first: a random row drawn from ``generator``).
    Their summed coverage is the largest any ``count`` rows have."""
    left = torch.ones(len(coverage), dtype=torch.bool)
    nearest = torch.full((len(coverage),), float("inf"), dtype=directions.dtype)
    chosen: list[int] = []
    for _ in range(min(count, len(coverage))):
        top = torch.nonzero(left & (coverage == coverage[left].max())).flatten()
        pick = int(top[torch.randint(len(top), (1,), generator=generator)] if not chosen
                   else top[torch.argmax(nearest[top])])
        chosen.append(pick)
        left[pick] = False
        nearest = torch.minimum(nearest, (directions - directions[pick]).norm(dim=-1))
    return chosen


def lights_sharing_views(present: Tensor, first: int, num_views: int, num_lights: int,
                         light_dirs: Tensor) -> list[int] | None:
    """``num_lights`` lights, starting at ``first``, under all of which at least ``num_views`` views were imaged
    (``present [V,L]``): each next light is the one farthest (smallest distance to those picked, on ``light_dirs``)
    among the lights that keep ``num_views`` such views; ``None`` when none does."""
    lights = [first]
    common = present[:, first].clone()
    while len(lights) < num_lights:
        keeps = (present & common[:, None]).sum(0) >= num_views
        keeps[lights] = False
        if not keeps.any():
            return None
        candidates = torch.nonzero(keeps).flatten()
        gaps = torch.cdist(light_dirs[candidates], light_dirs[lights]).min(dim=1).values
        pick = int(candidates[torch.argmax(gaps)])
        lights.append(pick)
        common &= present[:, pick]
    return lights if int(common.sum()) >= num_views else None


def captured_together(present: Tensor, lights: list[int], num_views: int, view_dirs: Tensor, light_dirs: Tensor,
                      generator: torch.Generator, rounds: int = 8) -> tuple[list[int], list[int]]:
    """Views and lights of an incomplete lattice ``present [V,L]`` that share the most captured images found.

    Lights first: :func:`lights_sharing_views` started at each of ``lights`` (farthest-point picks), then at every
    other captured light; the first start that succeeds gives ``len(lights)`` lights and the ``num_views`` views
    imaged under all of them, spread by farthest-point sampling (:func:`most_covered`). When no start succeeds:
    from ``lights``, the ``num_views`` views imaged under the most of them, then the lights imaged in the most of
    those views, and so on while the count of captured ``(view, light)`` pairs grows (at most ``rounds`` times)."""
    num_lights = len(lights)
    captured = torch.nonzero(present.any(0)).flatten().tolist()
    for first in lights + [light for light in captured if light not in lights]:
        shared = lights_sharing_views(present, first, num_views, num_lights, light_dirs)
        if shared is not None:
            return most_covered(present[:, shared].sum(1), view_dirs, num_views, generator), shared
    best_pairs, best = -1, ([], lights)
    for _ in range(rounds):
        views = most_covered(present[:, lights].sum(1), view_dirs, num_views, generator)
        pairs = int(present[views][:, lights].sum())
        if pairs <= best_pairs:
            break
        best_pairs, best = pairs, (views, lights)
        lights = most_covered(present[views].sum(0), light_dirs, num_lights, generator)
    return best


def _key_value(part: str, spec: str) -> tuple[str, str]:
    if "=" not in part:
        raise ValueError(f"regime '{spec}': '{part}' is not of the form key=value")
    key, value = part.split("=", 1)
    return key.strip(), value.strip()


def _select_images(dataset: OLATDataset, spec: str, seed: int, count: int, view_dirs: Tensor,
                   light_dirs: Tensor, generator: torch.Generator) -> RegimeSelection:
    """Farthest-point sampling over observations in the joint (view direction, light direction) space."""
    if count < 1:
        raise ValueError(f"regime '{spec}': images must be >= 1")
    if count > len(dataset.observations):
        raise ValueError(f"regime: '{spec}' asks for {count} images; the capture has {len(dataset.observations)}")
    views = torch.tensor([obs.view for obs in dataset.observations])
    lights = torch.tensor([obs.light for obs in dataset.observations])
    joint = torch.cat([view_dirs[views], light_dirs[lights]], dim=-1)
    chosen = sorted(farthest_point_order(joint, count, generator))
    return _from_observations(dataset, spec, seed, chosen)


def _from_observations(dataset: OLATDataset, spec: str, seed: int, indices) -> RegimeSelection:
    indices = sorted(int(i) for i in indices)
    views = sorted({dataset.observations[i].view for i in indices})
    lights = sorted({dataset.observations[i].light for i in indices})
    return RegimeSelection(spec=spec, seed=seed, views=views, lights=lights, observations=indices)
