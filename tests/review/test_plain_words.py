"""The card review page's words (review.plain_words, issue 33.1): the strings the grader, the
orientation step and the crowd's aggregation write, turned into sentences a curator reads."""

from __future__ import annotations

from annotation.aggregation import BoxConsensus, ConfidenceRules, unconfident_reasons
from review.plain_words import (
    certainty_words,
    crowd_reason_words,
    cue_words,
    flag_words,
    grade_reason_words,
    orientation_evidence_words,
)


def test_a_posterior_below_the_bar_reads_as_how_sure_the_model_is() -> None:
    reasons = "; ".join(unconfident_reasons({"inverted": 0.722}, rules=ConfidenceRules()))
    assert reasons == "inverted: posterior 0.722 < 0.95"  # what aggregation stores
    assert crowd_reason_words(reasons, {"inverted": True}) == [
        "a negative? the crowd says yes; the model is 72% sure (it decides alone from 95%)"
    ]
    assert crowd_reason_words(reasons) == ["a negative? the model is 72% sure (it decides alone from 95%)"]


def test_box_disagreements_read_in_pixels_and_overlap() -> None:
    spread = BoxConsensus(box=(0, 0, 10, 10), kept=3, dropped=0, kept_mask=(True,) * 3, mad=(42.8, 1, 1, 1), mean_iou=0.78)
    reasons = "; ".join(unconfident_reasons(boxes={"left": spread}))
    assert crowd_reason_words(reasons) == [
        "left box: the annotators' boxes differ by up to 43 px (it decides alone within 8 px)",
        "left box: the annotators' boxes overlap 78% on average (it decides alone from 80%)",
    ]
    assert crowd_reason_words("something new: 3 > 2") == ["something new: 3 > 2"]  # passed through, not lost


def test_the_orientation_steps_cues_lose_their_weights_and_names() -> None:
    assert cue_words("ground_plane: disparity grows towards the top: turned (-0.22 x 2.95)") == (
        "the ground tilts the wrong way: it comes nearer towards the top"
    )
    assert (
        cue_words("warm_tone: warm (sepia/buff) tones: a positive (+0.98 x 2.23)")
        == "the tone: warm (sepia/buff) tones: a positive"
    )
    assert flag_words("upside_down", 0.014) == "upside down: the orientation step is 99% sure it is not"
    assert flag_words("swapped", 0.72) == "photos in the wrong eye order: the orientation step is 72% sure it is"
    lines = orientation_evidence_words({"inverted": {"p": 0.0, "evidence": ["sky_top: top darker (+0.1 x 1)"]}, "bad": None})
    assert lines == ["a negative: the orientation step is 100% sure it is not (the sky: top darker)"]


def test_grade_reasons_name_measurements_in_words() -> None:
    reason = "few: every measurement within thresholds; nearest: dy_p95_px 1.9 px is 0.14 px from its some threshold (> 2 px)"
    assert grade_reason_words(reason) == (
        "few artifacts: every measurement within thresholds; nearest: vertical misalignment after rectification 1.9 px "
        "is 0.14 px from its some threshold (> 2 px)"
    )
    # Plain words that are also measurement names stay as written ("eyes swapped" once read
    # "eyes photos exchanged").
    depth = "some: the top comes out nearer (upside down, eyes swapped, or a near blob high up); coverage is full"
    assert grade_reason_words(depth) == (
        "some artifacts: the top comes out nearer (upside down, eyes swapped, or a near blob high up); coverage is full"
    )
    assert [certainty_words(u) for u in (0.95, 0.5, 0.1, None)] == [
        "a close call: a measurement is right at its limit",
        "fairly sure",
        "sure",
        "",
    ]


def test_the_card_page_says_why_the_crowd_waits_in_words(app, client, login, make_card, add_stage_result, card_image) -> None:  # type: ignore[no-untyped-def]
    from annotation.batches import create_batch
    from annotation.models import Aggregate
    from core.db import db
    from review.tasks import sync_reviews

    card_id = make_card(card_image(), state="pass")
    add_stage_result(card_id, "grade", outcome="some", metrics={"uncertainty": 0.3, "reasons": ["some: fringes"]})
    with app.app_context():
        sync_reviews()
        batch = create_batch([card_id], "judge", 3, 0.0)
        db.session.add(
            Aggregate(
                batch_id=batch.id,
                card_id=card_id,
                kind="judge",
                state="needs_curator",
                answers=3,
                label={"is_stereo": True, "upside_down": False, "inverted": False},
                posterior={"inverted": [0.722, 0.278]},
                reasons="inverted: posterior 0.722 < 0.95",
            )
        )
        db.session.commit()
    login("curator")
    page = client.get(f"/review/cards/{card_id}").get_data(as_text=True)
    words = page[page.index('id="crowd-words"') : page.index("</ul>", page.index('id="crowd-words"'))]
    assert "a negative? the crowd says no; the model is 72% sure (it decides alone from 95%)" in words
    # the raw reason stays available, behind the details disclosure
    assert page.index('id="review-details"') < page.index("inverted: posterior 0.722 &lt; 0.95")
