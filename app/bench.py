"""``keystone bench ...``: the benchmarks that check the speed targets (numbers over adjectives)."""

from __future__ import annotations

from pathlib import Path

import click


@click.group("bench")
def bench_group() -> None:
    """Benchmarks of pipeline stages on real images (medians over repeats, one core)."""


@bench_group.command("filter")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 100),
              help="Runs per card; the median is reported.")
@click.option("--shared-data", type=click.Path(path_type=Path, file_okay=False),
              help="Folder with the real test cards (../shared/data); default: found next to the checkout, "
                   "else synthetic cards from scikit-image's Motorcycle pair.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def bench_filter(repeats: int, shared_data: Path | None, as_json: bool) -> None:
    """Seconds per card on one core for the split + SIFT filter, split into detect and match."""
    from pipeline.bench import benchmark_filter, default_bench_cards

    from .console import emit_json

    if shared_data is None:
        candidate = Path(__file__).resolve().parents[2] / "shared" / "data"
        shared_data = candidate if candidate.is_dir() else None
    cards = default_bench_cards(shared_data)
    document = benchmark_filter(cards, repeats=repeats)
    if as_json:
        emit_json(document)
        return
    click.echo(f"{'card':<56} {'half':>10} {'split':>7} {'detect':>7} {'match':>7} {'total':>7}")
    for row in document["results"]:
        size = "x".join(str(v) for v in row["half_size"])
        click.echo(f"{row['card'][:56]:<56} {size:>10} {row['split_seconds']:7.3f} {row['detect_seconds']:7.3f} "
                   f"{row['match_seconds']:7.3f} {row['total_seconds']:7.3f}")
    click.echo(f"median total {document['median_total_seconds']:.3f} s per card "
               f"(target <= {document['target_seconds']} s, one core)")

