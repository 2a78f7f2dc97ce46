"""Training the intensity and depth networks: the loss (Liu et al. 2018, equations 3-7, less the
perceptual and style terms) and a resumable training loop whose batches, flips and learning rate
depend on the step alone. Conventions in :mod:`pipeline.inpainting`."""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from ..errors import InvalidInputError
from .checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from .network import InpaintConfig, build_network, network_inputs, pad_to_multiple
from .samples import Sample

if TYPE_CHECKING:
    import torch


class TrainingResult(TypedDict):
    """What :func:`train` returns."""

    step: int  # the last step done
    start_step: int  # the step it resumed from (0 for a fresh run)
    losses: list[list[float]]  # per step since step 0: [intensity loss, depth loss]
    seconds: float
    checkpoint: str | None  # path of checkpoint.pt, None without an output folder
    networks: list[torch.nn.Module]  # [intensity, depth], in eval mode


def inpainting_loss(
    output: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    known: torch.Tensor | None = None,
    hole_weight: float = 6.0,
    tv_weight: float = 0.1,
) -> torch.Tensor:
    """``mean(K M |O-G|) + hole_weight mean(K (1-M) |O-G|) + tv_weight TV(M G + (1-M) O)`` over
    tensors of the same shape (N, 1, H, W); ``mask`` M = 1 on known input pixels; ``known`` K = 1
    where ground truth exists (default all). Returns a scalar tensor."""
    import torch

    k = torch.ones_like(mask) if known is None else known
    err = (output - target).abs() * k
    valid = (mask * err).mean()
    hole = ((1 - mask) * err).mean()
    comp = mask * target + (1 - mask) * output
    tv = (comp[..., :, 1:] - comp[..., :, :-1]).abs().mean() + (comp[..., 1:, :] - comp[..., :-1, :]).abs().mean()
    return valid + hole_weight * hole + tv_weight * tv


def stack_samples(samples: list[Sample], multiple: int) -> tuple[np.ndarray, ...]:
    """The samples as padded (N, C, H, W) float32 arrays: network inputs, masks, guides, and the
    intensity, D^ and known-pixel targets."""
    xs, ms, gs, its, ds, ks = [], [], [], [], [], []
    for s in samples:
        x, m = network_inputs(s.intensity, s.dhat, s.hole, s.boundary)
        xs.append(pad_to_multiple(x, multiple)[0])
        ms.append(pad_to_multiple(m * s.known[None], multiple)[0])  # unknown (invalid) pixels are not inputs
        gs.append(pad_to_multiple(s.guide(), multiple)[0])
        its.append(pad_to_multiple(s.intensity[None], multiple)[0])
        ds.append(pad_to_multiple(s.dhat[None], multiple)[0])
        ks.append(pad_to_multiple(s.known[None], multiple)[0])
    return tuple(np.stack(a) for a in (xs, ms, gs, its, ds, ks))


def train(
    samples: list[Sample],
    config: InpaintConfig,
    out_dir: str | os.PathLike[str] | None,
    resume: bool = True,
    stop_at: int | None = None,
) -> TrainingResult:
    """Train the intensity and depth networks (Adam) for ``config.steps`` steps in total.

    Each step draws a batch of ``config.batch_size`` samples from a generator seeded by
    ``(config.seed, step)``, so a run resumed from a checkpoint continues exactly as an
    uninterrupted one. Every ``config.checkpoint_every`` steps and at the end, model + optimiser +
    step + configuration are written atomically to ``out_dir/checkpoint.pt`` (and the configuration to
    ``config.json``); with ``resume`` an existing checkpoint there is loaded and training continues
    from its step. ``stop_at`` pauses after that step (checkpoint written), as an interruption
    would. The learning rate follows ``config.schedule`` over ``config.steps`` (cosine:
    ``lr (1 + cos(pi step / steps)) / 2``), a function of the step alone, so an interrupted and
    resumed run with the same configuration matches an uninterrupted one (resuming with a larger
    ``steps`` stretches the rest of the schedule). Flips (``config.augment``) come from the same
    per-step generator. Returns ``{"step", "start_step", "losses" (per step: [intensity, depth]),
    "seconds", "checkpoint", "networks"}``."""
    import torch

    if not samples:
        raise InvalidInputError("no training samples (no holes from double reprojection)")
    torch.manual_seed(config.seed)
    nets = [build_network(config, "intensity"), build_network(config, "depth")]
    opts = [torch.optim.Adam(n.parameters(), lr=config.lr) for n in nets]
    out = Path(out_dir) if out_dir is not None else None
    start = 0
    losses: list[list[float]] = []
    if out is not None and resume and (out / CHECKPOINT_NAME).is_file():
        stored, _, _, state = load_checkpoint(out)
        if stored.architecture() != config.architecture():
            raise InvalidInputError(
                f"the checkpoint in {out} has another architecture (depth, width, guided) = "
                f"{stored.architecture()}, not {config.architecture()}: train without resume or into another folder"
            )
        nets[0].load_state_dict(state["intensity"])
        nets[1].load_state_dict(state["depth"])
        opts[0].load_state_dict(state["opt_intensity"])
        opts[1].load_state_dict(state["opt_depth"])
        start, losses = int(state["step"]), list(state.get("losses", []))
    multiple = 2**config.depth
    x, m, g, gi, gd, k = (torch.from_numpy(a) for a in stack_samples(samples, multiple))
    for n in nets:
        n.train()
    t0 = time.perf_counter()
    gen = torch.Generator()
    step = start
    end = config.steps if stop_at is None else max(start, min(config.steps, stop_at))
    while step < end:
        gen.manual_seed(config.seed * 1_000_003 + step)
        idx = torch.randint(len(samples), (config.batch_size,), generator=gen)
        flips = torch.randint(2, (2,), generator=gen).tolist() if config.augment else [0, 0]
        dims = [d for d, f in zip((-1, -2), flips) if f]
        batch = [t[idx] for t in (x, m, g, gi, gd, k)]
        if dims:  # the flip of a disocclusion is a disocclusion seen from the mirrored camera
            batch = [t.flip(dims) for t in batch]
        bx, bm, bg, bi, bd, bk = batch
        lr = config.lr * (0.5 * (1.0 + math.cos(math.pi * step / config.steps)) if config.schedule == "cosine" else 1.0)
        row = []
        for net, opt, target in ((nets[0], opts[0], bi), (nets[1], opts[1], bd)):
            for group in opt.param_groups:
                group["lr"] = lr
            opt.zero_grad()
            o = net(bx, bm, bg if config.guided else None)
            loss = inpainting_loss(o, target, bm, bk, config.hole_weight, config.tv_weight)
            loss.backward()
            opt.step()
            row.append(float(loss.detach()))
        losses.append(row)
        step += 1
        if out is not None and (step % config.checkpoint_every == 0 or step == end):
            save_checkpoint(out, step, config, nets, opts, losses)
    if out is not None and step == start and not (out / CHECKPOINT_NAME).is_file():
        save_checkpoint(out, step, config, nets, opts, losses)
    for n in nets:
        n.eval()
    return {
        "step": step,
        "start_step": start,
        "losses": losses,
        "seconds": time.perf_counter() - t0,
        "checkpoint": str(out / CHECKPOINT_NAME) if out is not None else None,
        "networks": nets,
    }
