"""The crowd's blueprint (annotation/blueprint.py): the task pages, the confirm grid and the
curators' pages each add their routes to it, and none imports another for it."""

from __future__ import annotations

from benchmarks.import_graph import import_graph, strongly_connected_components


def test_no_cycle_among_the_crowd_modules() -> None:
    graph = import_graph()
    crowd = {
        name: {t for t in targets if t.startswith("annotation.")}
        for name, targets in graph.items()
        if name.startswith("annotation.")
    }
    cycles = [sorted(c) for c in strongly_connected_components(crowd) if len(c) > 1]
    assert cycles == []
    assert "annotation.views" not in graph["annotation.staff_views"]
    assert "annotation.staff_views" not in graph["annotation.views"]
    assert "annotation.blueprint" in graph["annotation.staff_views"] & graph["annotation.views"] & graph["annotation.grid_views"]


def test_the_blueprint_carries_the_routes_of_all_three_modules(app) -> None:  # type: ignore[no-untyped-def]
    endpoints = {rule.endpoint for rule in app.url_map.iter_rules()}
    # views (a task page and its API), grid_views (the grid's API), staff_views (batches, CSV).
    assert {"crowd.invite", "crowd.api_submit", "crowd.api_grid_submit", "crowd.batches", "crowd.answers_csv"} <= endpoints
