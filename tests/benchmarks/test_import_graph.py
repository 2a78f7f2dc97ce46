"""The module import graph (benchmarks/import_graph.py), counting imports inside functions: no
import cycle at all, no arrow up the layer table, and docs/ARCHITECTURE.md's package map as the
code says it is."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import import_graph as graph_module
from benchmarks.import_graph import (
    ARCHITECTURE_DOC,
    LAYERS,
    PRODUCT_PACKAGES,
    Layer,
    cycle_edges,
    cycles,
    describe_edge,
    generated_part,
    import_graph,
    markdown,
    module_files,
    package_map,
    product_graph,
    strongly_connected_components,
    summary,
    upward_edges,
)

REGENERATE = "python -m benchmarks.import_graph --write-docs"


def test_strongly_connected_components_on_a_known_graph() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": {"e"}, "e": {"d"}, "f": {"a"}}
    components = sorted(sorted(c) for c in strongly_connected_components(graph))
    assert components == [["a", "b", "c"], ["d", "e"], ["f"]]
    assert cycles(graph) == [["a", "b", "c"], ["d", "e"]] and cycles({"x": set()}) == []
    assert cycle_edges(graph, ["d", "e"]) == [("d", "e"), ("e", "d")]


def test_imports_inside_functions_count(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("def f():\n    from . import b\n    return b\n")
    (tmp_path / "pkg" / "b.py").write_text("from pkg.a import f\n")
    graph = import_graph(tmp_path, ("pkg",))
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.b"]]


def test_an_arrow_up_the_layer_table_is_found(monkeypatch: pytest.MonkeyPatch) -> None:
    layers = (Layer("low", "kernel", ""), Layer("mid", "feature", ""), Layer("top", "composition root", ""))
    monkeypatch.setattr(graph_module, "LAYERS", layers)
    monkeypatch.setattr(graph_module, "LAYER_INDEX", {layer.package: i for i, layer in enumerate(layers)})
    graph = {"low.a": {"mid.b"}, "mid.b": {"low.a", "mid.c"}, "mid.c": set(), "top": {"mid.b", "low.a"}}
    assert upward_edges(graph) == [("low.a", "mid.b")]
    assert describe_edge("low.a", "mid.b") == "low.a -> mid.b (kernel low -> feature mid)"


def test_every_package_has_a_place_in_the_layer_table() -> None:
    repo = ARCHITECTURE_DOC.parent.parent
    packages = {path.parent.name for path in repo.glob("*/__init__.py")}
    assert packages == {layer.package for layer in LAYERS}, "a new top-level package needs its row in LAYERS"
    assert LAYERS[0].package == "pipeline" and LAYERS[-1].package == "benchmarks"


def test_the_pure_core_imports_no_other_package() -> None:
    assert set(package_map(import_graph()).get("pipeline", {})) == set()


def test_there_is_no_import_cycle() -> None:
    graph = import_graph()
    found = cycles(graph)
    lines = [f"{len(c)} modules: " + ", ".join(f"{s} -> {t}" for s, t in cycle_edges(graph, c)) for c in found]
    assert found == [], f"{len(found)} import cycle(s), imports inside functions included:\n  " + "\n  ".join(lines)


def test_no_import_climbs_the_layer_table() -> None:
    edges = upward_edges(import_graph())
    order = " < ".join(layer.package for layer in LAYERS)
    message = "\n  ".join(describe_edge(s, t) for s, t in edges)
    assert edges == [], f"{len(edges)} import(s) up the layers ({order}):\n  {message}"


def test_module_summaries_come_from_the_first_sentence_of_the_docstring(tmp_path: Path) -> None:
    path = tmp_path / "m.py"
    path.write_text('"""Crop alignment (Luo et al.): :func:`align` and ``x | y``. More.\n\nLater."""\n')
    assert summary(path) == "Crop alignment (Luo et al.): `align` and `x \\| y`."
    path.write_text("x = 1\n")
    assert summary(path) == ""


def test_every_product_module_appears_in_the_architecture_doc() -> None:
    document = ARCHITECTURE_DOC.read_text(encoding="utf-8")
    modules = module_files()
    shown = {name: f"`{name}/`" if modules[name].is_package and "." not in name else f"`{name}`" for name in modules}
    missing = sorted(name for name in product_graph(import_graph()) if shown[name] not in document)
    assert missing == [], f"docs/ARCHITECTURE.md lacks {missing}: run {REGENERATE}"
    assert {name.split(".")[0] for name in modules} >= set(PRODUCT_PACKAGES)


def test_the_generated_package_map_is_current() -> None:
    document = ARCHITECTURE_DOC.read_text(encoding="utf-8")
    assert generated_part(document) == markdown(), f"docs/ARCHITECTURE.md's package map is stale: run {REGENERATE}"
