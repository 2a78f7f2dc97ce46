"""``keystone bench ...``: the benchmarks that check the speed targets (numbers over adjectives).

Benchmarks in the top-level ``benchmarks`` package are loaded only when their command runs (or
``keystone bench --help`` lists them), so the product never imports them.
"""

from __future__ import annotations

import importlib

import click

# command name -> "module:attribute" of its click command in the benchmarks package
LAZY_BENCHMARKS = {
    "catalogue": "benchmarks.catalogue:bench_catalogue_command",
    "confirm-grid": "benchmarks.confirm_grid:bench_confirm_grid_command",
    "crowd": "benchmarks.crowd:bench_crowd_command",
    "disparity": "benchmarks.disparity:bench_disparity_command",
    "driver": "benchmarks.driver:bench_driver_command",
    "export": "benchmarks.export:bench_export_command",
    "filter": "benchmarks.filter:bench_filter_command",
    "grade": "benchmarks.grade:bench_grade_command",
    "grade-real": "benchmarks.grade_real:bench_grade_real_command",
    "iiif": "benchmarks.iiif:bench_iiif_command",
    "inpainting": "benchmarks.inpainting:bench_inpainting_command",
    "invariance": "benchmarks.invariance:bench_invariance_command",
    "pipeline": "benchmarks.pipeline_cost:bench_pipeline_command",
    "probe": "benchmarks.probe:bench_probe_command",
    "rectify": "benchmarks.rectify:bench_rectify_command",
    "views": "benchmarks.views:bench_views_command",
    "walks": "benchmarks.walks:bench_walks_command",
    "workres": "benchmarks.workres:bench_workres_command",
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
                    f"which this install does not have ({exc})"
                ) from exc
            self.add_command(getattr(module, attribute), cmd_name)
        return super().get_command(ctx, cmd_name)


@click.group("bench", cls=BenchGroup)
def bench_group() -> None:
    """Benchmarks of pipeline stages on real images (medians over repeats, one core)."""


def register_cli(group: click.Group) -> None:
    """Add ``bench`` to ``group`` (the ``keystone`` command); its benchmarks load when they run."""
    group.add_command(bench_group)
