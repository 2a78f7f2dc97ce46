"""The module import graph (benchmarks/import_graph.py), counting imports inside functions: no
cycle crosses a package boundary, and a ratchet on the one cycle left inside app/."""

from __future__ import annotations

from pathlib import Path

from benchmarks.import_graph import (
    PRODUCT_PACKAGES,
    import_graph,
    largest_cycle,
    package_map,
    strongly_connected_components,
)

# Largest strongly connected component of the product's module graph when this test was written:
# core.auth and core.security import each other (inside functions). It may only shrink.
LARGEST_CYCLE_NOW = 2


def _product_graph() -> dict[str, set[str]]:
    graph = import_graph()
    return {
        name: {t for t in targets if t.split(".")[0] in PRODUCT_PACKAGES}
        for name, targets in graph.items()
        if name.split(".")[0] in PRODUCT_PACKAGES
    }


def test_strongly_connected_components_on_a_known_graph() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": {"e"}, "e": {"d"}, "f": {"a"}}
    components = sorted(sorted(c) for c in strongly_connected_components(graph))
    assert components == [["a", "b", "c"], ["d", "e"], ["f"]]
    assert largest_cycle(graph) == {"a", "b", "c"} and largest_cycle({"x": set()}) == set()


def test_imports_inside_functions_count(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("def f():\n    from . import b\n    return b\n")
    (tmp_path / "pkg" / "b.py").write_text("from pkg.a import f\n")
    graph = import_graph(tmp_path, ("pkg",))
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert largest_cycle(graph) == {"pkg.a", "pkg.b"}


def test_the_pure_core_and_the_benchmarks_stay_out_of_every_cycle() -> None:
    graph = import_graph()
    assert set(package_map(graph).get("pipeline", {})) == set()  # pipeline imports no other package
    cycle = largest_cycle(_product_graph())
    assert not any(name.split(".")[0] == "pipeline" for name in cycle)
    for component in strongly_connected_components(graph):
        if len(component) > 1:
            assert not any(name.startswith("benchmarks") for name in component), component


def test_no_cycle_crosses_a_package_boundary() -> None:
    for component in strongly_connected_components(_product_graph()):
        assert len({name.split(".")[0] for name in component}) == 1, sorted(component)


def test_the_cycle_inside_app_does_not_grow() -> None:
    cycle = largest_cycle(_product_graph())
    assert len(cycle) <= LARGEST_CYCLE_NOW, sorted(cycle)
