"""``keystone bench disparity``: error against run time of the disparity backends.

Wire with ``bench_group.add_command(bench_disparity_command)`` (the command is named "disparity").
No database is needed.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.disparity import BACKENDS


@click.command("disparity")
@click.option("--scene", "scenes", multiple=True, type=click.Path(path_type=Path, file_okay=False, exists=True),
              help="MiddEval3 scene folder (im0.png, im1.png, disp0GT.pfm, optional mask0nocc.png); repeatable. "
                   "Default: Motorcycle (scikit-image) plus Tsukuba and Adirondack from ../shared/data/stereo_gt "
                   "when present.")
@click.option("--backend", "backends", multiple=True, type=click.Choice(BACKENDS),
              help="Backend to run; repeatable. Default: all.")
@click.option("--perturbation", "perturbations", multiple=True,
              type=click.Choice(("none", "down2", "down4", "rot0.5")),
              help="Right-view perturbation; repeatable. Default: all four.")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 100),
              help="Runs per case; the median time is reported.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
@click.option("--plot", type=click.Path(path_type=Path, dir_okay=False),
              help="Write a PNG of mean bad-2 against seconds with the Pareto front (needs matplotlib).")
def bench_disparity_command(scenes: tuple[Path, ...], backends: tuple[str, ...], perturbations: tuple[str, ...],
                            repeats: int, as_json: bool, plot: Path | None) -> None:
    """EPE, bad-1, bad-2 and coverage over valid ground truth at full coverage, and seconds (one core)."""
    import json

    from pipeline.disparity_bench import (
        PERTURBATIONS,
        benchmark_disparity,
        builtin_scenes,
        load_middeval3,
        plot_pareto,
    )
    from pipeline.errors import PipelineError

    try:
        loaded = [load_middeval3(s) for s in scenes] if scenes else builtin_scenes()
        document = benchmark_disparity(loaded, backends=backends or BACKENDS,
                                       perturbations=perturbations or PERTURBATIONS, repeats=repeats)
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    if plot is not None:
        try:
            document["pareto_front"] = plot_pareto(document["summary"], plot)
        except ImportError as exc:
            raise click.ClickException(f"--plot needs matplotlib ({exc})") from exc
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False, default=_nan_safe))
        return
    click.echo(f"{'scene':<14} {'perturbation':<12} {'backend':<14} {'epe':>7} {'bad1%':>7} {'bad2%':>7} "
               f"{'cover%':>7} {'conf%':>7} {'seconds':>8}")
    for r in document["results"]:
        click.echo(f"{r['scene'][:14]:<14} {r['perturbation']:<12} {r['backend']:<14} {r['epe']:7.2f} "
                   f"{r['bad1']:7.1f} {r['bad2']:7.1f} {r['coverage']:7.1f} {r['confident_coverage']:7.1f} "
                   f"{r['seconds']:8.3f}")
    click.echo("")
    click.echo(f"{'backend':<14} {'mean epe':>9} {'mean bad2%':>11} {'cover%':>7} {'median s':>9} {'s@741x500':>10}")
    for s in document["summary"]:
        click.echo(f"{s['backend']:<14} {s['epe']:9.2f} {s['bad2']:11.1f} {s['coverage']:7.1f} {s['seconds']:9.3f} "
                   f"{s['seconds_741x500']:10.3f}")
    click.echo(f"default backend: {document['default_backend']} (target: mean bad-2 <= "
               f"{document['target']['mean_bad2']} % at <= {document['target']['seconds_741x500']} s per 741x500 pair)")
    if plot is not None:
        click.echo(f"plot: {plot} (Pareto front: {', '.join(document['pareto_front'])})")


def _nan_safe(value):  # pragma: no cover - numpy scalars only
    return float(value)
