"""The package structure: no package imports one that imports it back; the trainer is no hub."""

from __future__ import annotations

import ast
from pathlib import Path

import diamond_sss

SOURCE = Path(diamond_sss.__file__).parent
# packages whose modules must not reach the training loop (they read finished runs or build on the scene)
NOT_THE_TRAINER = ("scene", "rendering", "shading", "gaussians", "evaluation", "viewer", "diffusion")


def module_name(path: Path) -> str:
    parts = path.relative_to(SOURCE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_of(module: str) -> str | None:
    """``diamond_sss.<package>`` (``diffusion.<part>`` for the diffusion sub-packages); None outside."""
    parts = module.split(".")
    if parts[0] != "diamond_sss" or len(parts) < 2 or not (SOURCE / parts[1]).is_dir():
        return None
    return ".".join(parts[1:3]) if parts[1] == "diffusion" and len(parts) > 2 else parts[1]


def imports_of(path: Path) -> set[str]:
    """Every absolute ``diamond_sss`` module a file imports, at any depth (function-level imports too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {name for name in found if name.startswith("diamond_sss.")}


def package_graph() -> dict[str, dict[str, set[str]]]:
    """``graph[a][b]``: the modules of package ``a`` that import package ``b``."""
    graph: dict[str, dict[str, set[str]]] = {}
    for path in sorted(SOURCE.rglob("*.py")):
        source = package_of(module_name(path))
        for target in filter(None, map(package_of, imports_of(path))):
            if source is not None and target != source:
                graph.setdefault(source, {}).setdefault(target, set()).add(module_name(path))
    return graph


def reachable(graph: dict[str, dict[str, set[str]]], start: str) -> set[str]:
    seen, stack = set(), [start]
    while stack:
        for nxt in graph.get(stack.pop(), {}):
            if nxt not in seen:
                seen.add(nxt)
                stack.append(nxt)
    return seen


def test_package_graph_helpers_known_answer():
    assert package_of("diamond_sss.training.trainer") == "training"
    assert package_of("diamond_sss.diffusion.nvs.model") == "diffusion.nvs"
    assert package_of("diamond_sss.errors") is None and package_of("torch.nn") is None
    graph = {"a": {"b": {"a.x"}}, "b": {"c": {"b.y"}}, "c": {"a": {"c.z"}}}
    assert reachable(graph, "a") == {"a", "b", "c"} and reachable({"a": {"b": set()}}, "b") == set()


def test_no_package_imports_one_that_imports_it_back():
    graph = package_graph()
    assert {"training", "evaluation", "scene", "shading", "viewer"} <= set(graph)
    cycles = {package: sorted(graph[package]) for package in graph if package in reachable(graph, package)}
    assert not cycles, f"packages on an import cycle (package -> what it imports): {cycles}"


def test_only_training_jobs_import_the_trainer():
    offenders = sorted(
        module_name(path) for path in SOURCE.rglob("*.py")
        if package_of(module_name(path)) and package_of(module_name(path)).split(".")[0] in NOT_THE_TRAINER
        and "diamond_sss.training.trainer" in imports_of(path)
    )
    assert not offenders, f"these modules import the training loop (use diamond_sss.training.run_folder): {offenders}"


def test_the_diffusion_models_import_nothing_from_the_reconstruction_training_package():
    """diffusion/ stands beside training/: the checkpoint helpers they share live in utils/, the finished-run reader
    in runs/."""
    offenders = sorted(
        f"{module_name(path)} imports {name}"
        for path in (SOURCE / "diffusion").rglob("*.py")
        for name in imports_of(path)
        if name == "diamond_sss.training" or name.startswith("diamond_sss.training.")
    )
    assert not offenders, f"diffusion modules import the training package: {offenders}"
    graph = package_graph()
    assert {"diffusion.nvs", "diffusion.relight", "diffusion.geometry"} <= set(graph)
    assert not [package for package in graph if package.startswith("diffusion") and "training" in graph[package]]
