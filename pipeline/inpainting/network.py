"""The inpainting networks: their configuration, the partial convolution (Liu et al. 2018,
equations 1-2) and the partial-convolution U-Net, guided by a classical fill. Conventions in
:mod:`pipeline.inpainting`. torch is imported inside the functions only."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InvalidInputError

if TYPE_CHECKING:
    import torch

GUIDE_CHANNELS = 2  # classical_init's (intensity, D^)


@dataclass(frozen=True)
class InpaintConfig:
    """Network and training configuration (stored with every checkpoint)."""

    depth: int = 3  # U-Net levels (input side must be a multiple of 2**depth; inputs are padded)
    width: int = 16  # channels at the first level (doubling per level)
    batch_size: int = 8
    lr: float = 2e-3
    steps: int = 200
    checkpoint_every: int = 50
    seed: int = 0
    hole_weight: float = 6.0
    tv_weight: float = 0.1
    guided: bool = True  # refine a classical fill (residual) instead of inpainting from scratch
    schedule: str = "cosine"  # learning rate over the steps: "cosine" (to 0 at config.steps) or "constant"
    augment: bool = True  # random horizontal / vertical flips of each batch

    def __post_init__(self) -> None:
        if self.schedule not in ("cosine", "constant"):
            raise InvalidInputError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        if self.depth < 1 or self.width < 1 or self.batch_size < 1 or self.steps < 0 or self.checkpoint_every < 1:
            raise InvalidInputError(f"bad inpainting configuration {self!r}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise InvalidInputError(f"lr must be finite and > 0, got {self.lr!r}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> InpaintConfig:
        """From a stored configuration; keys a checkpoint written before they existed take the
        values that reproduce that checkpoint (an unguided network, constant rate, no flips)."""
        return cls(**{**_LEGACY, **{k: v for k, v in d.items() if k in cls.__dataclass_fields__}})

    def architecture(self) -> tuple[int, int, bool]:
        """What must match for a state dict to load: (depth, width, guided)."""
        return (self.depth, self.width, self.guided)


_LEGACY = {"guided": False, "schedule": "constant", "augment": False}


def partial_conv2d(
    x: torch.Tensor, mask: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None, stride: int = 1, padding: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Partial convolution (Liu et al. 2018). ``x`` (N, C, H, W), ``mask`` (N, 1, H, W) in {0, 1},
    ``weight`` (O, C, k, k). Returns ``(out, new_mask)``: ``out = conv(x * mask) * k*k / sum(mask)
    + b`` where ``sum(mask) > 0``, else 0; ``new_mask`` = 1 where ``sum(mask) > 0``."""
    import torch
    import torch.nn.functional as F

    kh, kw = weight.shape[2], weight.shape[3]
    with torch.no_grad():
        ones = torch.ones(1, 1, kh, kw, dtype=mask.dtype, device=mask.device)
        msum = F.conv2d(mask, ones, stride=stride, padding=padding)
        new_mask = (msum > 0).to(mask.dtype)
        ratio = (kh * kw) / msum.clamp(min=1.0) * new_mask
    out = F.conv2d(x * mask, weight, None, stride=stride, padding=padding) * ratio
    if bias is not None:
        out = out + bias.view(1, -1, 1, 1)
    return out * new_mask, new_mask


def build_network(config: InpaintConfig, channel: str = "depth") -> torch.nn.Module:
    """A partial-convolution U-Net (one output channel) as a ``torch.nn.Module``:
    ``net(x, mask, guide=None) -> output`` with ``x`` (N, 3, H, W) = (I M, D^ M, B M), ``mask``
    (N, 1, H, W) and, for a guided network, ``guide`` (N, 2, H, W) = :func:`classical_init`'s
    (intensity, D^) fill; H and W multiples of ``2**config.depth``. Encoder: per level a stride-2
    partial conv (5x5 first, then 3x3) + ReLU; decoder: nearest upsampling, concatenation with the
    skip, 3x3 partial conv + LeakyReLU(0.2); a final 3x3 partial conv to one channel (linear).

    Guided (``config.guided``): the first layer adds an ordinary 5x5 stride-2 convolution of the
    guide to the partial convolution of the masked inputs (the holes still contribute nothing
    through ``x``; the mask logic applies to them), after which every position carries information
    and the mask is all ones; the full-resolution skip also carries the guide and the mask; the
    output is ``guide[channel] + residual`` with the last layer initialised to zero, so an
    untrained network returns the classical fill exactly and training only has to correct it.
    ``channel``: which guide channel the output refines ("intensity" or "depth")."""
    import torch
    from torch import nn

    if channel not in ("intensity", "depth"):
        raise InvalidInputError(f"channel must be 'intensity' or 'depth', got {channel!r}")

    class PConv(nn.Module):
        def __init__(self, cin: int, cout: int, k: int, stride: int) -> None:
            super().__init__()
            self.conv = nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2)
            self.stride, self.padding = stride, k // 2

        def forward(self, x: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return partial_conv2d(x, m, self.conv.weight, self.conv.bias, self.stride, self.padding)

    class PartialUNet(nn.Module):
        def __init__(self, depth: int, width: int, guided: bool, out_index: int) -> None:
            super().__init__()
            chans = [3] + [width * 2**i for i in range(depth)]
            skip0 = 3 + GUIDE_CHANNELS + 1 if guided else 3  # (x, guide, mask) at full resolution
            self.enc = nn.ModuleList(PConv(chans[i], chans[i + 1], 5 if i == 0 else 3, 2) for i in range(depth))
            self.dec = nn.ModuleList(
                PConv(chans[i + 1] + (chans[i] if i > 0 else skip0), chans[i] if i > 0 else width, 3, 1)
                for i in reversed(range(depth))
            )
            self.out = PConv(width, 1, 3, 1)
            self.guide_in = nn.Conv2d(GUIDE_CHANNELS, chans[1], 5, stride=2, padding=2, bias=False) if guided else None
            if guided:
                nn.init.zeros_(self.out.conv.weight)
                if self.out.conv.bias is not None:  # Conv2d has one unless bias=False
                    nn.init.zeros_(self.out.conv.bias)
            self.depth, self.guided, self.out_index = depth, guided, out_index

        def forward(self, x: torch.Tensor, m: torch.Tensor, guide: torch.Tensor | None = None) -> torch.Tensor:
            if self.guided and guide is None:
                raise InvalidInputError("a guided inpainting network needs the classical fill as guide")
            skips = [(torch.cat([x, guide, m], 1), torch.ones_like(m)) if guide is not None and self.guided else (x, m)]
            h, hm = x, m
            for i, layer in enumerate(self.enc):
                h, hm = layer(h, hm)
                if i == 0 and self.guide_in is not None and guide is not None:
                    h = h + self.guide_in(guide)
                    hm = torch.ones_like(hm)
                h = torch.relu(h)
                skips.append((h, hm))
            skips.pop()
            for layer in self.dec:
                s, sm = skips.pop()
                h = nn.functional.interpolate(h, size=s.shape[-2:], mode="nearest")
                hm = nn.functional.interpolate(hm, size=s.shape[-2:], mode="nearest")
                h, hm = layer(torch.cat([h, s], 1), torch.maximum(hm, sm))
                h = nn.functional.leaky_relu(h, 0.2)
            out: torch.Tensor = self.out(h, torch.ones_like(hm))[0]
            if guide is not None and self.guided:
                out = out + guide[:, self.out_index : self.out_index + 1]
            return out

    return PartialUNet(config.depth, config.width, config.guided, 0 if channel == "intensity" else 1)


def network_inputs(
    intensity: np.ndarray, dhat: np.ndarray, hole: np.ndarray, boundary: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(3, H, W) network input ``(I M, D^ M, B M)`` and (1, H, W) mask ``M = 1 - hole``, float32."""
    m = 1.0 - hole
    x = np.stack([intensity * m, dhat * m, boundary * m]).astype(np.float32)
    return x, m[None].astype(np.float32)


def pad_to_multiple(arr: np.ndarray, multiple: int) -> tuple[np.ndarray, int, int]:
    """``arr`` (..., H, W) zero-padded at the bottom and right to multiples of ``multiple`` (the
    U-Net halves the size ``depth`` times); returns ``(padded, H, W)`` to crop the output back."""
    h, w = arr.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        arr = np.pad(arr, [(0, 0)] * (arr.ndim - 2) + [(0, ph), (0, pw)])
    return arr, h, w
