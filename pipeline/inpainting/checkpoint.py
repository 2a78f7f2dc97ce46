"""Writing and loading the inpainting networks: model, optimiser, step and configuration in one
file written atomically, so an interrupted training run resumes from its last checkpoint."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

from ..errors import InvalidInputError
from .network import InpaintConfig, build_network

if TYPE_CHECKING:
    import torch

CHECKPOINT_NAME = "checkpoint.pt"
CONFIG_NAME = "config.json"

# (configuration, intensity network, depth network, the whole stored state)
Checkpoint: TypeAlias = "tuple[InpaintConfig, torch.nn.Module, torch.nn.Module, dict[str, Any]]"


def save_checkpoint(
    out_dir: Path,
    step: int,
    config: InpaintConfig,
    nets: Sequence[torch.nn.Module],
    opts: Sequence[torch.optim.Optimizer],
    losses: list[list[float]],
) -> None:
    """``out_dir/checkpoint.pt`` (networks, optimisers, step, configuration, losses so far),
    written atomically, and the configuration alone in ``out_dir/config.json``."""
    import torch

    from ..io import atomic_write, write_json

    state = {
        "step": step,
        "config": asdict(config),
        "losses": losses,
        "intensity": nets[0].state_dict(),
        "depth": nets[1].state_dict(),
        "opt_intensity": opts[0].state_dict(),
        "opt_depth": opts[1].state_dict(),
    }
    with atomic_write(out_dir / CHECKPOINT_NAME) as handle:
        torch.save(state, handle)
    write_json(out_dir / CONFIG_NAME, {"config": asdict(config), "step": step})


def load_checkpoint(path: str | os.PathLike[str]) -> Checkpoint:
    """Load a checkpoint file (or a folder holding ``checkpoint.pt``): returns
    ``(config, intensity_net, depth_net, state)`` with both networks in eval mode."""
    import torch

    p = Path(path)
    if p.is_dir():
        p = p / CHECKPOINT_NAME
    if not p.is_file():
        raise InvalidInputError(f"no inpainting checkpoint at {p}")
    state: dict[str, Any] = torch.load(p, map_location="cpu", weights_only=True)
    config = InpaintConfig.from_dict(state["config"])
    nets = []
    for key in ("intensity", "depth"):
        net = build_network(config, key)
        net.load_state_dict(state[key])
        net.eval()
        nets.append(net)
    return config, nets[0], nets[1], state
