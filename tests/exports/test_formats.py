"""The release formats' registry (exports/formats/): the built-in formats find themselves, and a
format registered from outside is written by a release, described in croissant.json and checked
by verify without any other module knowing its name."""

from __future__ import annotations

import hashlib
import json
import pkgutil
from pathlib import Path
from typing import Any

import pytest

from exports.croissant import jsonl_record_set
from exports.formats import Problems, ReleaseFormat, WriteContext
from exports.writers import CardPayload, FileLedger

BUILT_IN = ("keystonedepth", "parquet", "webdataset", "views", "stereo", "iiif")


class ToyWriter:
    """``toy/<key>.txt`` per card (its id and grade) and ``toy/toy.jsonl``, one line per card."""

    def __init__(self, ledger: FileLedger) -> None:
        self.ledger = ledger
        self.keys: list[str] = []

    def add(self, payload: CardPayload) -> None:
        card = payload.card
        self.ledger.write_bytes(f"toy/{card.key}.txt", f"{card.card_id} {card.grade}\n".encode())
        self.keys.append(card.key)

    def close(self) -> None:
        self.ledger.write_bytes("toy/toy.jsonl", b"".join(json.dumps({"key": key}).encode() + b"\n" for key in self.keys))

    def summary(self) -> dict[str, Any]:
        return {"cards": len(self.keys)}


class ToyFormat(ReleaseFormat):
    name = "toy"
    description = "a text file per card"
    order = 99
    encodings = {".txt": "text/plain"}
    reports = True

    def writer(self, context: WriteContext) -> ToyWriter:
        return ToyWriter(context.ledger)

    def readme_layout(self, summary: dict[str, Any] | None) -> list[str]:
        return [f"- `toy/<id>.txt`: the card's id and grade, for {(summary or {})['cards']} cards."]

    def changelog(self, summary: dict[str, Any] | None) -> list[str]:
        return ["", f"### Toy ({(summary or {})['cards']} cards)"]

    def record_sets(self, summary: dict[str, Any] | None, card_count: int) -> list[dict[str, Any]]:
        fields = (("key", "sc:Text", "The card's key: its file is toy/<key>.txt."),)
        return [jsonl_record_set("toy", fields, f"A text file for {(summary or {})['cards']} of {card_count} cards.")]

    def verify(self, root: Path, listed: dict[str, str], problems: Problems) -> None:
        files = sorted(p for p in listed if p.startswith("toy/") and p.endswith(".txt"))
        if not files and "toy/toy.jsonl" not in listed:
            return
        keys = [json.loads(line)["key"] for line in (root / "toy/toy.jsonl").read_text().splitlines()]
        if sorted(keys) != [p[len("toy/") : -len(".txt")] for p in files]:
            problems.problem("toy/toy.jsonl", f"lists {len(keys)} card(s), toy/ holds {len(files)} file(s)")


@pytest.fixture
def toy_format(monkeypatch: pytest.MonkeyPatch) -> ToyFormat:
    from exports.formats import registry

    registry.registered_formats()  # the built-in formats first
    fmt = ToyFormat()
    monkeypatch.setitem(registry.REGISTRY, fmt.name, fmt)
    return fmt


def _publish(app, out: Path, **options):  # type: ignore[no-untyped-def]
    from exports.release import publish_release

    with app.app_context():
        return publish_release(out, **options)


def test_every_module_of_the_package_registers_one_format_in_the_canonical_order() -> None:
    import exports.formats
    from exports.formats import default_format_names, format_names, registered_formats
    from exports.formats.registry import NOT_FORMAT_MODULES

    assert format_names() == BUILT_IN
    assert default_format_names() == ("keystonedepth", "parquet", "iiif")
    modules = {
        f"exports.formats.{module.name}"
        for module in pkgutil.iter_modules(exports.formats.__path__)
        if module.name not in NOT_FORMAT_MODULES
    }
    assert sorted(type(fmt).__module__ for fmt in registered_formats()) == sorted(modules)
    assert all(fmt.description and fmt.description == fmt.description.strip() for fmt in registered_formats())


def test_a_reporting_format_does_not_shadow_a_key_of_the_release_report() -> None:
    from exports.formats import registered_formats
    from exports.release import ReleaseReport

    report = ReleaseReport(
        version="1.0.0",
        path=None,
        cards=0,
        formats=[],
        min_grade="some",
        date="",
        changes={},
        grades={},
        excluded=[],
        seconds=0.0,
    )
    own_keys = set(report.as_json()) - {fmt.name for fmt in registered_formats() if fmt.reports}
    assert {"version", "cards", "formats", "stereo"} - own_keys == {"stereo"}
    assert not own_keys & {fmt.name for fmt in registered_formats()}


def test_format_names_are_parsed_into_the_canonical_order() -> None:
    from exports.formats import chosen_formats, parse_formats

    assert parse_formats("stereo, keystonedepth,views") == ("keystonedepth", "views", "stereo")
    assert [fmt.name for fmt in chosen_formats(["parquet", "webdataset"])] == ["parquet", "webdataset"]
    with pytest.raises(
        ValueError, match="Expected formats from keystonedepth, parquet, webdataset, views, stereo, iiif, got csv"
    ):
        parse_formats("keystonedepth,csv")
    with pytest.raises(ValueError, match="got none"):
        parse_formats(" , ")


def test_the_decorator_registers_and_refuses_a_second_format_of_the_same_name(monkeypatch: pytest.MonkeyPatch) -> None:
    from exports.formats import registry

    registry.registered_formats()
    monkeypatch.setattr(registry, "REGISTRY", {})

    @registry.release_format
    class Csv(ToyFormat):
        name = "csv"

    assert registry.get_format("csv").name == "csv" and registry.format_names() == ("csv",)

    class OtherCsv(ToyFormat):
        name = "csv"

    with pytest.raises(ValueError, match="Two release formats are named 'csv'"):
        registry.register_format(OtherCsv())

    class Bad(ToyFormat):
        name = "Bad,name"

    with pytest.raises(ValueError, match="lowercase format name without commas"):
        registry.register_format(Bad())
    with pytest.raises(ValueError, match="got 'keystonedepth'"):
        registry.get_format("keystonedepth")


def test_two_formats_may_not_give_one_suffix_two_types(monkeypatch: pytest.MonkeyPatch, toy_format: ToyFormat) -> None:
    from exports.formats import format_encodings, registry

    assert format_encodings()[".txt"] == "text/plain" and format_encodings()[".mpo"] == "image/mpo"

    class Markdown(ToyFormat):
        name = "markdown"
        encodings = {".txt": "text/markdown"}

    monkeypatch.setitem(registry.REGISTRY, "markdown", Markdown())
    with pytest.raises(ValueError, match=r"give \.txt files different types"):
        format_encodings()


def test_a_registered_format_is_written_described_and_verified(app, tmp_path, processed_cards, review_card, toy_format) -> None:
    from exports.verify import verify_release

    ids = processed_cards(2)
    for card_id in ids:
        review_card(card_id, "few")
    report = _publish(app, tmp_path / "out", formats="toy,keystonedepth")
    root = Path(report.path)
    keys = [f"{card_id:05d}" for card_id in ids]

    # Written by the release, in the canonical order of formats, and in the report.
    assert report.formats == ["keystonedepth", "toy"]
    assert [(root / f"toy/{key}.txt").read_text() for key in keys] == [f"{card_id} few\n" for card_id in ids]
    assert report.as_json()["toy"] == {"cards": 2} and report.as_json()["views"] is None
    sums = (root / "SHA256SUMS").read_text()
    for relative in (*(f"toy/{key}.txt" for key in keys), "toy/toy.jsonl"):
        assert f"{hashlib.sha256((root / relative).read_bytes()).hexdigest()}  {relative}\n" in sums
    assert "- `toy/<id>.txt`: the card's id and grade, for 2 cards." in (root / "README.md").read_text()
    assert "### Toy (2 cards)" in (root / "CHANGELOG.md").read_text()

    # Described in croissant.json: its files with their type, its record set after the cards.
    croissant = json.loads((root / "croissant.json").read_text())
    assert [record_set["@id"] for record_set in croissant["recordSet"]] == ["cards", "toy"]
    toy_set = croissant["recordSet"][1]
    assert toy_set["description"] == "A text file for 2 of 2 cards."
    assert toy_set["field"][0]["source"]["fileObject"]["@id"] == "file/toy/toy.jsonl"
    described = {entry["contentUrl"]: entry["encodingFormat"] for entry in croissant["distribution"]}
    assert described[f"toy/{keys[0]}.txt"] == "text/plain"

    # Checked by verify: sound as written; a toy file gone (and unlisted) is named by the toy's check.
    assert verify_release(root).as_json()["problems"] == []
    (root / f"toy/{keys[1]}.txt").unlink()
    (root / "SHA256SUMS").write_text("".join(line + "\n" for line in sums.splitlines() if not line.endswith(".txt")))
    problems = verify_release(root, validate_croissant=False).problems
    assert {"path": "toy/toy.jsonl", "problem": "lists 2 card(s), toy/ holds 0 file(s)"} in problems


def test_format_options_reach_the_writer(app, tmp_path, processed_cards, review_card, monkeypatch) -> None:
    import pyarrow.parquet as pq

    from exports.formats import registry
    from exports.formats.parquet import ParquetFormat, ParquetOptions

    ids = processed_cards(2)
    for card_id in ids:
        review_card(card_id, "few")
    assert registry.get_format("parquet").options == ParquetOptions()
    monkeypatch.setitem(registry.REGISTRY, "parquet", ParquetFormat(ParquetOptions(row_group_cards=1)))
    report = _publish(app, tmp_path / "out", formats=("parquet",))
    shard = pq.ParquetFile(Path(report.path) / "data/train-00000-of-00001.parquet")
    assert shard.metadata.num_row_groups == 2 and shard.metadata.num_rows == 2
