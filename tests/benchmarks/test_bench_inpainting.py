"""benchmarks.inpainting: ``keystone bench inpainting`` (L1 in held-out holes, network vs classical)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

pytest.importorskip("torch")

from benchmarks.inpainting import bench_inpainting_command, benchmark_inpainting


def test_bench_inpainting_json_shape():
    result = CliRunner().invoke(bench_inpainting_command, ["--json", "--steps", "5", "--size", "32"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    pairs = {(r["method"], r["channel"]) for r in doc["results"]}
    assert pairs == {(m, c) for m in ("network", "telea", "navier-stokes", "none") for c in ("intensity", "depth")}
    assert all(r["l1"] is not None and r["l1"] >= 0 for r in doc["results"])
    assert doc["training_seconds"] > 0 and doc["steps"] == 5 and doc["test_samples"] > 0
    assert isinstance(doc["network_beats_classical_on_depth"], bool)
    inits = {(r["method"], r["channel"]): r["l1"] for r in doc["init_results"]}
    assert set(inits) == {("navier-stokes", "intensity"), ("background-fill", "depth")}
    # the intensity init is Navier-Stokes itself: the same fill, the same error
    assert inits[("navier-stokes", "intensity")] == pytest.approx(
        next(r["l1"] for r in doc["results"] if r["method"] == "navier-stokes" and r["channel"] == "intensity")
    )
    paired = doc["depth_per_sample"]
    assert paired["samples"] == doc["test_samples"] and 0 <= paired["network_beats_best_classical"] <= paired["samples"]
    low, high = paired["bootstrap_ci95"]
    assert low <= paired["l1_difference_vs_best_classical"] <= high


@pytest.mark.bench
def test_shipped_bench_network_beats_classical_on_depth():
    doc = benchmark_inpainting()
    by = {(r["method"], r["channel"]): r["l1"] for r in doc["results"]}
    assert by[("network", "depth")] < min(by[("telea", "depth")], by[("navier-stokes", "depth")])
    assert by[("network", "depth")] < by[("none", "depth")]
    assert doc["network_beats_classical_on_depth"] is True
