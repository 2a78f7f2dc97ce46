"""``keystone train-inpainting``: train the hole-filling networks of the views stage.

Added to ``keystone`` as "train-inpainting". Training reads the catalogue only with
``--source catalogue``; the benchmark of the networks is ``keystone bench inpainting``
(``benchmarks/inpainting.py``).
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np


def catalogue_gd_images() -> list:
    """The v0 grey + depth image of every card whose latest views result is done (the reference
    view: real pixels; its depth is the disparity's, with the few missing pixels filled)."""
    import json as json_module

    from flask import current_app
    from sqlalchemy import select

    from core.db import db, read_only
    from core.models import StageResult
    from pipeline.errors import PipelineError
    from pipeline.io import read_image, to_grey
    from pipeline.views import make_gd_image

    data_dir = Path(current_app.config["KEYSTONE_DATA_DIR"])
    latest: dict[int, StageResult] = {}
    with read_only():
        for result in db.session.scalars(select(StageResult).where(StageResult.stage == "views").order_by(StageResult.id)):
            latest[result.card_id] = result
        done = [r for r in latest.values() if r.status == "done"]
    images = []
    for result in done:
        try:
            scene = json_module.loads((data_dir / result.artifacts["scene"]).read_text())
            focal = float(scene["views"][0]["focal_px"])
            grey = read_image(data_dir / result.artifacts["v0"])
            depth = np.load(data_dir / result.artifacts["v0_depth"])
            images.append(make_gd_image(to_grey(grey), depth, focal))  # the networks are grey; views may be colour
        except (KeyError, OSError, ValueError, PipelineError) as exc:
            click.echo(f"skipping card {result.card_id}: its views cannot be read ({exc})", err=True)
    return images


@click.command("train-inpainting")
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(path_type=Path, file_okay=False),
    help="Folder for checkpoint.pt (model + optimiser + step + config) and config.json.",
)
@click.option(
    "--steps",
    default=300,
    show_default=True,
    type=click.IntRange(1, 10_000_000),
    help="Total training steps (a resumed run continues up to this step).",
)
@click.option("--size", default=64, show_default=True, type=click.IntRange(16, 1024), help="Crop side in px.")
@click.option("--batch-size", default=8, show_default=True, type=click.IntRange(1, 4096))
@click.option("--checkpoint-every", default=50, show_default=True, type=click.IntRange(1, 10_000_000))
@click.option("--resume/--no-resume", default=True, show_default=True, help="Continue from OUT/checkpoint.pt when it exists.")
@click.option(
    "--source",
    type=click.Choice(["builtin", "catalogue"]),
    default="builtin",
    show_default=True,
    help="builtin: scikit-image's Motorcycle; catalogue: the v0 GD images of every card whose "
    "views stage is done (keystone run --stages views).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout and nothing else.")
def train_inpainting_command(
    out_dir: Path, steps: int, size: int, batch_size: int, checkpoint_every: int, resume: bool, source: str, as_json: bool
) -> None:
    """Train the intensity and depth partial-convolution networks on double-reprojection holes of
    GD images, with atomic checkpoints and resume: the built-in ones (scikit-image's Motorcycle
    crops) or the catalogue's own (--source catalogue). The networks refine a classical fill
    (residual) with a cosine learning rate over --steps: an interrupted run resumed with the same
    --steps continues exactly."""
    from dataclasses import asdict

    from pipeline.errors import PipelineError
    from pipeline.inpainting import (
        InpaintConfig,
        builtin_gd_images,
        crop_gd_images,
        make_samples,
        train,
    )

    config = InpaintConfig(steps=steps, batch_size=batch_size, checkpoint_every=checkpoint_every, depth=3 if size >= 32 else 2)
    try:
        if source == "catalogue":
            from flask.cli import ScriptInfo

            # Only this source needs the app (the built-in images need no database).
            with click.get_current_context().ensure_object(ScriptInfo).load_app().app_context():
                train_gd = crop_gd_images(catalogue_gd_images(), size)
            if not train_gd:
                raise click.ClickException(
                    "no usable GD images in the catalogue: run `keystone run --stages views` "
                    "first (cards graded failure get none)"
                )
        else:
            train_gd, _ = builtin_gd_images(size)
        result = train(make_samples(train_gd), config, out_dir, resume=resume)
    except PipelineError as exc:
        raise click.ClickException(exc.reason()) from exc
    losses = result["losses"]
    document = {
        "step": result["step"],
        "start_step": result["start_step"],
        "seconds": round(result["seconds"], 3),
        "source": source,
        "gd_crops": len(train_gd),
        "checkpoint": result["checkpoint"],
        "config": asdict(config),
        "last_loss": losses[-1] if losses else None,
    }
    if as_json:
        click.echo(json.dumps(document, indent=2, allow_nan=False))
        return
    click.echo(
        f"trained steps {result['start_step']}..{result['step']} in {result['seconds']:.1f} s; "
        f"checkpoint {result['checkpoint']}; last loss (intensity, depth) {document['last_loss']}"
    )
