"""The module import graph of the product packages, counting imports inside functions.

Reads the source with ``ast`` (nothing is imported), so a lazy ``import`` inside a function
counts as an edge like a top-level one: what matters for layering is who may call whom, not
when the import runs. Reports the package-level map (which top-level package imports which),
the largest strongly connected component of the module graph (Tarjan 1972), and the largest
modules by line count.

    python -m benchmarks.import_graph [--json]
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

PRODUCT_PACKAGES = ("app", "core", "runs", "catalogue", "annotation", "review", "exports", "pipeline")
ALL_PACKAGES = (*PRODUCT_PACKAGES, "benchmarks")
REPO_ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class ModuleFile:
    name: str  # dotted module name, e.g. "pipeline.stages.base"
    path: Path
    is_package: bool


def module_files(root: Path = REPO_ROOT, packages: Iterable[str] = ALL_PACKAGES) -> dict[str, ModuleFile]:
    """Every ``.py`` file under the given top-level packages, by dotted module name."""
    found: dict[str, ModuleFile] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if "migrations" in parts:  # Alembic revision scripts are loaded by path, not imported
                continue
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            found[".".join(parts)] = ModuleFile(".".join(parts), path, is_package)
    return found


def _resolve(name: str, known: dict[str, ModuleFile]) -> str | None:
    """The longest known module that ``name`` is or lies inside (``a.b.func`` -> ``a.b``)."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in known:
            return candidate
        parts.pop()
    return None


def imported_modules(module: ModuleFile, known: dict[str, ModuleFile]) -> set[str]:
    """Known modules that ``module`` imports anywhere in its body (functions included)."""
    tree = ast.parse(module.path.read_text(encoding="utf-8"), filename=str(module.path))
    package = module.name if module.is_package else module.name.rpartition(".")[0]
    targets: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            # "from pkg import sub" imports the submodule pkg.sub; "from pkg import name" needs pkg
            # itself (for a module inside pkg, "from . import sibling" adds no edge to its package).
            names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for name in names:
            resolved = _resolve(name, known)
            if resolved is not None and resolved != module.name:
                targets.add(resolved)
    return targets


def import_graph(root: Path = REPO_ROOT, packages: Iterable[str] = ALL_PACKAGES) -> dict[str, set[str]]:
    known = module_files(root, packages)
    return {name: imported_modules(module, known) for name, module in known.items()}


def strongly_connected_components(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm, iterative (the graph's depth would pass Python's recursion limit)."""
    index: dict[str, int] = {}
    lowlink: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[set[str]] = []
    counter = 0
    for start in graph:
        if start in index:
            continue
        work: list[tuple[str, list[str]]] = [(start, sorted(graph[start]))]
        index[start] = lowlink[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            if successors:
                succ = successors.pop()
                if succ not in graph:
                    continue
                if succ not in index:
                    index[succ] = lowlink[succ] = counter
                    counter += 1
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, sorted(graph[succ])))
                elif succ in on_stack:
                    lowlink[node] = min(lowlink[node], index[succ])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                lowlink[parent] = min(lowlink[parent], lowlink[node])
            if lowlink[node] == index[node]:
                component: set[str] = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                components.append(component)
    return components


def largest_cycle(graph: dict[str, set[str]]) -> set[str]:
    """The largest strongly connected component with more than one module (empty if none)."""
    cycles = [c for c in strongly_connected_components(graph) if len(c) > 1]
    return max(cycles, key=len, default=set())


def package_map(graph: dict[str, set[str]]) -> dict[str, dict[str, int]]:
    """For each top-level package, how many module-to-module imports go to each other package."""
    edges: dict[str, dict[str, int]] = {}
    for source, targets in graph.items():
        source_package = source.split(".")[0]
        for target in targets:
            target_package = target.split(".")[0]
            if target_package != source_package:
                row = edges.setdefault(source_package, {})
                row[target_package] = row.get(target_package, 0) + 1
    return {package: dict(sorted(row.items())) for package, row in sorted(edges.items())}


def largest_modules(root: Path = REPO_ROOT, count: int = 10) -> list[tuple[str, int]]:
    sizes = [(module.name, len(module.path.read_text(encoding="utf-8").splitlines())) for module in module_files(root).values()]
    return sorted(sizes, key=lambda item: -item[1])[:count]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    graph = import_graph()
    product = {
        k: {t for t in v if t.split(".")[0] in PRODUCT_PACKAGES} for k, v in graph.items() if k.split(".")[0] in PRODUCT_PACKAGES
    }
    cycle = largest_cycle(product)
    report = {
        "modules": len(graph),
        "package_map": package_map(graph),
        "largest_cycle_size": len(cycle),
        "largest_cycle": sorted(cycle),
        "largest_modules": largest_modules(),
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"modules: {report['modules']}")
    print("package map (imports from -> to, counted per module pair):")
    for source, row in report["package_map"].items():
        print(f"  {source:<11} -> " + ", ".join(f"{t} {n}" for t, n in row.items()))
    print(f"largest cycle: {len(cycle)} modules: {', '.join(sorted(cycle))}")
    print("largest modules (lines):")
    for name, lines in report["largest_modules"]:
        print(f"  {lines:>5}  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
