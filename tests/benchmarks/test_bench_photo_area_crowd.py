"""benchmarks.photo_area_crowd: the photo-area proposal against the simulated crowd's consensus."""

from __future__ import annotations

import json

from benchmarks.photo_area_crowd import iou, main, measure


def test_iou_of_boxes() -> None:
    assert iou((0, 0, 10, 10), (0, 0, 10, 10)) == 1.0
    assert iou((0, 0, 10, 10), (5, 0, 15, 10)) == 50 / 150
    assert iou((0, 0, 10, 10), (20, 20, 30, 30)) == 0.0


def test_proposals_match_the_crowd_consensus_on_simulated_cards() -> None:
    report = measure(cards=4, seed=7)
    assert report["halves"] == 8
    # the crowd (three honest annotators and a spammer) agrees with the truth to within a few px
    assert report["iou_consensus_truth"]["min"] > 0.95
    # the proposal lies inside every print and overlaps the consensus well (mean 0.85 on 24 cards)
    assert report["proposal_inside_print"] == 8
    assert report["iou_proposal_consensus"]["mean"] > 0.7
    assert all(0.0 <= r["iou_proposal_consensus"] <= 1.0 for r in report["rows"])


def test_cli_prints_json(capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["--cards", "1", "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["cards"] == 1 and "rows" not in document
