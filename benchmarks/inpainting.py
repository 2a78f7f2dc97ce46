"""``keystone bench inpainting``: L1 in held-out holes for the network and the classical fills.

Trains the partial-convolution networks of :mod:`pipeline.inpainting` briefly on
double-reprojection holes of built-in data, then compares them with OpenCV's Telea and
Navier-Stokes and with no inpainting, inside held-out holes.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict
from typing import Any

import click
import numpy as np

from pipeline.errors import InvalidInputError
from pipeline.inpainting import (
    METHODS,
    InpaintConfig,
    baseline_inpaint,
    builtin_gd_images,
    make_samples,
    run_networks,
    train,
)


def benchmark_inpainting(
    steps: int = 300, size: int = 64, config: InpaintConfig | None = None, out_dir: str | os.PathLike[str] | None = None
) -> dict[str, Any]:
    """Train briefly on double-reprojection holes of the training crops, then L1 inside the holes
    (over pixels with ground truth) on the held-out crops' holes for the network, Telea,
    Navier-Stokes and none, for intensity and D^. Returns the JSON-ready document."""
    import torch

    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    cfg = config or InpaintConfig(steps=steps, depth=3 if size >= 32 else 2, width=16, batch_size=8)
    if config is None:
        cfg = InpaintConfig.from_dict({**asdict(cfg), "steps": steps, "checkpoint_every": max(1, steps)})
    t0 = time.perf_counter()
    train_gd, test_gd = builtin_gd_images(size)
    train_samples, test_samples = make_samples(train_gd), make_samples(test_gd)
    prep = time.perf_counter() - t0
    if not train_samples or not test_samples:
        raise InvalidInputError("double reprojection left no holes in the built-in images")
    result = train(train_samples, cfg, out_dir, resume=False)
    nets = result["networks"]
    channels = ("intensity", "depth")
    # per held-out sample: (sum of |error| in its holes, pixel count) per (method, channel)
    per: dict[tuple[str, str], list[tuple[float, int]]] = {(m, c): [] for m in (*METHODS, "init") for c in channels}
    t1 = time.perf_counter()
    for s in test_samples:
        hole = s.hole > 0
        known = s.known > 0
        sel = hole & known
        if not sel.any():
            continue
        guide = s.guide()
        oi, od = run_networks(nets, s.intensity, s.dhat, s.hole, s.boundary, s.known, guide)
        inp = {"intensity": s.intensity, "depth": s.dhat}
        fill = hole | ~known
        for ci, (c, net_out) in enumerate((("intensity", oi), ("depth", od))):
            preds = {"network": np.where(fill, net_out, inp[c]), "init": guide[ci]}
            for mth in ("telea", "navier-stokes", "none"):
                preds[mth] = baseline_inpaint(np.where(fill, 0.0, inp[c]), fill, mth, c)
            for mth, p in preds.items():
                per[(mth, c)].append((float(np.abs(p - inp[c])[sel].sum()), int(sel.sum())))
    inference = time.perf_counter() - t1

    def l1(key: tuple[str, str]) -> float | None:
        n = sum(c for _, c in per[key])
        return sum(e for e, _ in per[key]) / n if n else None

    results = [{"method": m, "channel": c, "l1": l1((m, c))} for c in channels for m in METHODS]
    by = {(r["method"], r["channel"]): r["l1"] for r in results}
    beats = all(
        by[("network", "depth")] is not None and by[("network", "depth")] < by[(m, "depth")] for m in ("telea", "navier-stokes")
    )
    losses = result["losses"]
    return {
        "results": results,
        "init_results": [
            {"method": "background-fill" if c == "depth" else "navier-stokes", "channel": c, "l1": l1(("init", c))}
            for c in channels
        ],
        "depth_per_sample": _paired_summary(per, cfg.seed),
        "training_seconds": round(result["seconds"], 3),
        "inference_seconds": round(inference, 3),
        "preparation_seconds": round(prep, 3),
        "steps": result["step"],
        "size": size,
        "config": asdict(cfg),
        "train_samples": len(train_samples),
        "test_samples": len(test_samples),
        "hole_pixels": sum(c for _, c in per[("none", "depth")]),
        "first_loss": losses[0] if losses else None,
        "last_loss": [float(np.mean([row[i] for row in losses[-10:]])) for i in range(2)] if losses else None,
        "network_beats_classical_on_depth": bool(beats),
        "depth_l1_space": "normalised inverse depth D^ over known pixels",
        "threads": torch.get_num_threads(),
        "checkpoint": result["checkpoint"],
        "data": "scikit-image stereo_motorcycle (left + GT disparity); train = left 60 % + flips, test = right 40 %",
    }


def _paired_summary(per: dict[tuple[str, str], list[tuple[float, int]]], seed: int, resamples: int = 2000) -> dict[str, Any]:
    """Depth, per held-out sample: how often the network's hole L1 beats the best classical one
    (the lower of Telea and Navier-Stokes on that sample), and a bootstrap over samples (seeded) of
    the pooled difference network - min(Telea, Navier-Stokes) in D^ with its 95 % interval."""
    net = np.array(per[("network", "depth")], np.float64)
    if not len(net):
        return {"samples": 0}
    tel = np.array(per[("telea", "depth")], np.float64)
    ns = np.array(per[("navier-stokes", "depth")], np.float64)
    init = np.array(per[("init", "depth")], np.float64)
    n = net[:, 1]
    best = np.minimum(tel[:, 0], ns[:, 0])
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(n), (resamples, len(n)))
    diff = (net[draws, 0].sum(1) - np.minimum(tel[draws, 0].sum(1), ns[draws, 0].sum(1))) / n[draws].sum(1)
    return {
        "samples": len(n),
        "network_beats_best_classical": int((net[:, 0] < best).sum()),
        "network_beats_init": int((net[:, 0] < init[:, 0]).sum()),
        "l1_difference_vs_best_classical": float(net[:, 0].sum() / n.sum() - min(tel[:, 0].sum(), ns[:, 0].sum()) / n.sum()),
        "bootstrap_ci95": [float(np.quantile(diff, 0.025)), float(np.quantile(diff, 0.975))],
        "bootstrap_resamples": resamples,
    }


@click.command("inpainting")
@click.option(
    "--steps",
    default=300,
    show_default=True,
    type=click.IntRange(1, 1_000_000),
    help="Training steps (each trains both networks on one batch).",
)
@click.option("--size", default=64, show_default=True, type=click.IntRange(16, 1024), help="Side of the square GD crops in px.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def bench_inpainting_command(steps: int, size: int, as_json: bool) -> None:
    """L1 inside held-out double-reprojection holes for the partial-conv network, OpenCV Telea,
    Navier-Stokes and no inpainting, for intensity and depth (D^), plus training time (CPU). The
    networks refine a classical fill (background fill for depth, Navier-Stokes for intensity),
    whose own L1 is reported too, with a per-sample comparison and a bootstrap interval.
    Data: scikit-image's Motorcycle with its ground-truth disparity (train: left 60 % of the image
    and flips; test: the right 40 %)."""
    from pipeline.errors import PipelineError

    try:
        document = benchmark_inpainting(steps=steps, size=size)
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False))
        return
    click.echo(f"{'method':<14} {'channel':<10} {'L1 in holes':>12}")
    for r in document["results"]:
        l1 = "n/a" if r["l1"] is None else f"{r['l1']:.4f}"
        click.echo(f"{r['method']:<14} {r['channel']:<10} {l1:>12}")
    for r in document["init_results"]:
        l1 = "n/a" if r["l1"] is None else f"{r['l1']:.4f}"
        click.echo(f"  (the network's init: {r['method']} on {r['channel']}: {l1})")
    paired = document["depth_per_sample"]
    if paired.get("samples"):
        low, high = paired["bootstrap_ci95"]
        click.echo(
            f"depth, per held-out sample: network beats the better of Telea / Navier-Stokes on "
            f"{paired['network_beats_best_classical']} of {paired['samples']}; pooled L1 difference "
            f"{paired['l1_difference_vs_best_classical']:+.4f} (bootstrap 95 % CI {low:+.4f} .. {high:+.4f})"
        )
    click.echo(
        f"training: {document['steps']} steps in {document['training_seconds']:.1f} s "
        f"({document['train_samples']} train / {document['test_samples']} test samples, {size} px)"
    )
    click.echo(f"network beats Telea and Navier-Stokes on depth: {document['network_beats_classical_on_depth']}")
