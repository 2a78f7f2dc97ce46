"""The driver takes what it needs from the features through the registry, not by importing them."""

from __future__ import annotations

import ast
from pathlib import Path

from core.hooks import after_write, merged, stage_hooks, stage_params

ROOT = Path(__file__).resolve().parents[2]


def _imported_packages(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):  # inside functions too
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
    return names


def test_the_driver_and_the_registry_import_no_feature_package():
    # The whole driver (runs/) and the kernel (core/) with the registry; the layer table of
    # benchmarks/import_graph.py checks the same for every package.
    for path in sorted([*ROOT.glob("runs/*.py"), *ROOT.glob("core/*.py")]):
        assert not _imported_packages(path) & {"catalogue", "annotation", "review", "exports", "app"}, path


def test_features_register_what_a_run_needs(app):
    hooks = stage_hooks(app)
    assert sorted(p.__module__ for p in hooks.decisions) == ["annotation.run_hooks"] + ["review.run_hooks"] * 3
    assert sorted(p.__module__ for p in hooks.people_work) == ["annotation.run_hooks", "review.run_hooks"]
    assert set(hooks.stage_params) == {"grade"} and [h.__module__ for h in hooks.after_write["grade"]] == ["review.run_hooks"]


def test_providers_merge_per_card_and_hooks_run_in_order(app):
    with app.app_context():
        hooks = stage_hooks()
        calls: list[tuple[str, list[int]]] = []
        hooks.after_write.setdefault("unit", []).extend(
            [lambda ids: calls.append(("a", ids)), lambda ids: calls.append(("b", ids))]
        )
        after_write("unit", [3, 4])
        after_write("nobody-listens", [5])
        assert calls == [("a", [3, 4]), ("b", [3, 4])]
        first = lambda ids: {i: {"judge": f"j{i}"} for i in ids}  # noqa: E731
        second = lambda ids: {ids[0]: {"judge": "override", "review": "r"}}  # noqa: E731
        assert merged([first, second], [1, 2]) == {1: {"judge": "override", "review": "r"}, 2: {"judge": "j2"}}
        assert merged([first], []) == {}
        assert stage_params("unit", lambda: "default") == "default"
