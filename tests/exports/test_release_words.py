"""The releases pages' words for what a release changes (exports/release_words.py, issue 33.9)."""

from __future__ import annotations

from exports.release_words import release_summary, version_reason


def changes(previous: str | None = "1.2.0", kind: str = "patch", added=(), removed=(), changed=()) -> dict:  # type: ignore[no-untyped-def]
    return {
        "previous_version": previous,
        "kind": kind,
        "added": list(added),
        "removed": list(removed),
        "changed": [{"card_id": i, "why": ["grade changed (some -> few)"]} for i in changed],
    }


def test_a_release_that_only_adds_a_format_says_so() -> None:
    words = release_summary(changes(), ["keystonedepth", "parquet", "webdataset"], ["keystonedepth", "parquet"])
    assert words == "Format-only release: adds webdataset; same cards as 1.2.0."


def test_formats_added_and_dropped_are_both_named() -> None:
    words = release_summary(changes(), ["parquet", "views", "stereo"], ["keystonedepth", "parquet"])
    assert words == "Format-only release: adds views and stereo; drops keystonedepth; same cards as 1.2.0."


def test_a_format_only_patch_explains_its_version_by_the_release_rules() -> None:
    reason = version_reason(changes(), ["keystonedepth", "webdataset"], ["keystonedepth"])
    assert reason.startswith("A patch: the same cards with the same data (docs/RELEASES.md")
    assert "a format added or dropped writes the same cards' data in another form, so it is a patch" in reason
    assert "format added" not in version_reason(changes(), ["keystonedepth"], ["keystonedepth"])


def test_card_changes_are_counted_in_words() -> None:
    words = release_summary(changes(kind="major", added=[7], removed=[3, 4], changed=[5]), ["parquet"], ["parquet"])
    assert words == "Against 1.2.0: adds 1 card, removes 2 cards, changes 1 card."
    assert version_reason(changes(kind="minor", added=[7]), ["parquet"], ["parquet"]).startswith(
        "A minor release: it only adds cards"
    )


def test_cards_and_a_new_format_together_and_a_new_lowest_grade() -> None:
    words = release_summary(changes(kind="minor", added=[7, 8]), ["parquet", "webdataset"], ["parquet"], "few", "some")
    assert words == "Against 1.2.0: adds 2 cards; adds webdataset (lowest grade some → few)."


def test_the_same_data_again_and_the_first_release() -> None:
    assert release_summary(changes(), ["parquet"], ["parquet"]) == "Same cards and formats as 1.2.0: the same data written again."
    assert release_summary(changes(None, "first", added=[1, 2]), ["keystonedepth", "parquet"]) == (
        "First release: 2 cards in keystonedepth and parquet."
    )
    assert version_reason(changes(None, "first"), ["parquet"]) == "The first release is 1.0.0."
