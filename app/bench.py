"""``keystone bench ...``: the benchmarks that check the speed targets (numbers over adjectives).

Benchmarks in the top-level ``benchmarks`` package are loaded only when their command runs (or
``keystone bench --help`` lists them), so the product never imports them.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import click

# command name -> "module:attribute" of its click command in the benchmarks package
LAZY_BENCHMARKS = {
    "catalogue": "benchmarks.catalogue:bench_catalogue_command",
    "pipeline": "benchmarks.pipeline_cost:bench_pipeline_command",
}


class BenchGroup(click.Group):
    """A click group whose benchmark commands are imported on first use (click's lazy-group pattern)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *LAZY_BENCHMARKS})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in LAZY_BENCHMARKS and cmd_name not in self.commands:
            module_name, attribute = LAZY_BENCHMARKS[cmd_name].split(":")
            try:
                module = importlib.import_module(module_name)
            except ImportError as exc:
                raise click.ClickException(
                    f"the {cmd_name!r} benchmark lives in the source checkout's benchmarks/ folder, "
                    f"which this install does not have ({exc})") from exc
            self.add_command(getattr(module, attribute), cmd_name)
        return super().get_command(ctx, cmd_name)


@click.group("bench", cls=BenchGroup)
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

