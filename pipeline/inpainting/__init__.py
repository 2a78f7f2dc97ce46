"""Inpainting of reprojection holes: a partial-convolution U-Net (Liu et al., "Image Inpainting
for Irregular Holes Using Partial Convolutions", ECCV 2018) refining classical fills (OpenCV
Telea / Navier-Stokes, a background-biased depth fill, "none"), as KeystoneDepth (Luo et al.
2021, section 5) fills the holes of its novel views. One concept per module:

* :mod:`.network`: the configuration, the partial convolution and the U-Net;
* :mod:`.fill`: the classical fills, the normalised inverse depth, and filling a view with trained
  networks (:func:`inpaint`);
* :mod:`.checkpoint`: writing and loading the networks;
* :mod:`.samples`: training samples by double reprojection, and the built-in GD images;
* :mod:`.training`: the loss and the training loop (resumable).

torch is imported **lazily** (only inside functions): importing this package does not import torch.

Conventions
-----------
* Inputs per pixel: ``(I * M, D^ * M, B * M)`` with ``I`` the grey intensity in [0, 1], ``D^`` the
  normalised inverse depth, ``B`` the boundary mask on the foreground side of holes
  (:func:`pipeline.views.boundary_mask`) and ``M`` = 1 on known pixels (not a hole and valid).
* ``D^`` is normalised over the **known** pixels only (``(1/D - lo) / (hi - lo)``, lo/hi = min/max
  of 1/D over known pixels), so training and inference see the same statistics; the network's D^ in
  holes is mapped back to depth with the same lo/hi (clamped to a positive inverse depth).
* Partial convolution: ``out = W^T (X . M) * sum(1) / sum(M) + b`` where ``sum(M) > 0`` else 0;
  ``M' = 1`` where any known pixel lies in the window. One single-channel mask per layer (the
  input channels share it). In the decoder the skip and the upsampled path are concatenated and
  their masks combined by max (an approximation of Liu's per-channel masks).
* Losses (per network): ``mean(K M |O - G|) + 6 mean(K (1-M) |O - G|) + 0.1 TV(C)`` with ``O`` the
  output, ``G`` the ground truth, ``K`` the pixels with ground truth (valid depth), ``C = M G + (1-M) O``
  the composite and ``TV(C) = mean|C[:, 1:] - C[:, :-1]| + mean|C[1:, :] - C[:-1, :]|``. The
  perceptual and style terms of the paper are **omitted** (no feature network is available offline).
* Depth L1 in the benchmark is measured on D^ (normalised inverse depth, over known pixels).
* Guided networks (the default, ``InpaintConfig.guided``): each network also sees the classical
  fill of both channels (:func:`classical_init`: Navier-Stokes for intensity, :func:`background_fill`
  for D^, the farther depth wins, as a disocclusion shows the background) through an ordinary
  convolution in its first layer, and outputs that fill plus a learned residual (last layer
  zero-initialised: an untrained network is the classical fill). The partial convolution still
  sees the masked inputs only. On the 64 px benchmark the network from scratch lost to
  Navier-Stokes on depth (0.121 against 0.102); the guided one wins (``keystone bench inpainting``).
  Checkpoints written before these options load as unguided networks (:meth:`InpaintConfig.from_dict`).
"""

from __future__ import annotations

from .checkpoint import (
    CHECKPOINT_NAME,
    CONFIG_NAME,
    Checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from .fill import (
    METHODS,
    background_fill,
    baseline_inpaint,
    classical_init,
    inpaint,
    normalise_known,
    run_networks,
)
from .network import GUIDE_CHANNELS, InpaintConfig, build_network, partial_conv2d
from .samples import (
    MOTORCYCLE_FOCAL_PX,
    Sample,
    builtin_gd_images,
    crop_gd_images,
    make_samples,
)
from .training import TrainingResult, inpainting_loss, train

__all__ = [
    "CHECKPOINT_NAME",
    "CONFIG_NAME",
    "GUIDE_CHANNELS",
    "METHODS",
    "MOTORCYCLE_FOCAL_PX",
    "Checkpoint",
    "InpaintConfig",
    "Sample",
    "TrainingResult",
    "background_fill",
    "baseline_inpaint",
    "build_network",
    "builtin_gd_images",
    "classical_init",
    "crop_gd_images",
    "inpaint",
    "inpainting_loss",
    "load_checkpoint",
    "make_samples",
    "normalise_known",
    "partial_conv2d",
    "run_networks",
    "save_checkpoint",
    "train",
]
