"""``keystone bench rectify``: our Loop-Zhang rectification against OpenCV's Hartley
(``cv2.stereoRectifyUncalibrated``) on the same inputs.

Wire with ``bench_group.add_command(bench_rectify_command)`` (the command is named "rectify").
No database is needed.
"""

from __future__ import annotations

import json
from pathlib import Path

import click


def _fmt(value, spec: str) -> str:
    width = int(spec.split(".")[0] or 0)
    return "-".rjust(width) if value is None else format(value, spec)


@click.command("rectify")
@click.option("--shared-data", type=click.Path(path_type=Path, file_okay=False),
              help="Folder with the real pairs and stereo_gt (../shared/data); default: found next to the "
                   "checkout, else the Motorcycle synthetic pairs only.")
@click.option("--repeats", default=1, show_default=True, type=click.IntRange(1, 100),
              help="Runs per pair and method; the median time is reported.")
@click.option("--quick", is_flag=True, help="Motorcycle at half size, one synthetic warp (a few seconds).")
@click.option("--no-disparity", is_flag=True, help="Skip the disparity error on the synthetic pairs.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_rectify_command(shared_data: Path | None, repeats: int, quick: bool, no_disparity: bool,
                          as_json: bool) -> None:
    """Residual |dy|, distortion, disparity error (synthetic) and seconds per pair: keystone vs hartley."""
    from pipeline.errors import PipelineError
    from pipeline.rectify_bench import benchmark_rectify, default_pairs

    try:
        pairs = default_pairs(shared_data, quick=quick)
        document = benchmark_rectify(pairs, repeats=repeats, disparity=not no_disparity)
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False))
        return
    click.echo(f"{'pair':<44} {'method':<9} {'dy med':>7} {'dy p95':>7} {'midline':>8} {'aspect':>7} "
               f"{'epe':>6} {'bad2%':>6} {'gt dy95':>7} {'seconds':>8}  error")
    for r in document["results"]:
        click.echo(f"{r['pair'][:44]:<44} {r['method']:<9} {_fmt(r['dy_median'], '7.2f')} {_fmt(r['dy_p95'], '7.2f')} "
                   f"{_fmt(r['midline_deviation'], '8.2f')} {_fmt(r['aspect_change'], '7.3f')} "
                   f"{_fmt(r['epe'], '6.2f')} {_fmt(r['bad2'], '6.1f')} {_fmt(r['gt_dy_p95'], '7.2f')} "
                   f"{_fmt(r['seconds'], '8.3f')}  {r['error'] or ''}")
    summary = document["summary"]
    click.echo("")
    click.echo(f"medians over the {summary['compared_pairs']} pairs both methods rectified "
               "(midline = |midline angle - 90| deg, worse view):")
    click.echo(f"{'method':<9} {'kind':<10} {'pairs':>5} {'dy med':>7} {'dy p95':>7} {'midline':>8} {'aspect':>7} "
               f"{'epe':>6} {'bad2%':>6} {'seconds':>8} {'failures':>8}")
    for method in ("keystone", "hartley"):
        entry = summary[method]
        for kind in ("real", "synthetic"):
            s = entry[kind]
            click.echo(f"{method:<9} {kind:<10} {s['pairs']:>5} {_fmt(s['dy_median'], '7.2f')} {_fmt(s['dy_p95'], '7.2f')} "
                       f"{_fmt(s['midline_deviation'], '8.2f')} {_fmt(s['aspect_change'], '7.3f')} "
                       f"{_fmt(s['epe'], '6.2f')} {_fmt(s['bad2'], '6.1f')} {_fmt(s['seconds'], '8.3f')} "
                       f"{s['failures']:>8}")
    click.echo(f"keystone beats hartley on {summary['keystone_beats_hartley']} of {summary['compared_pairs']} pairs "
               f"({summary['criterion']})")
