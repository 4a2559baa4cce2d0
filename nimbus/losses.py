"""The differentiable training loss: (1 - lambda) L1 + lambda (1 - SSIM), with validity masks.

Images are torch tensors (H, W, 3) or (B, H, W, 3) in [0, 1].  The SSIM term is the metric's
(:func:`nimbus.metrics.mean_ssim`, the 3dgs protocol), so the loss optimises the SSIM that
training reports.  On the CPU, an unmasked single image pair takes the compiled kernel of
:mod:`nimbus.kernels.train_step` (the same loss and gradient up to float rounding, several times
faster); everything else, and every machine where it does not build, takes the torch ops.
"""

from __future__ import annotations

import torch

from nimbus.kernels import train_step
from nimbus.metrics.image import SSIM_C1, SSIM_C2, loss_taps, masked_pair, mean_ssim


def l1(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute difference, over the valid pixels when ``mask`` (bool ``(H, W)``) is given."""
    if mask is None:
        return (a - b).abs().mean()
    a, b, w = masked_pair(a, b, mask)
    return (a - b).abs().sum() / (w.expand_as(a).sum())


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float,
                     mask: torch.Tensor | None = None, gt_moments: torch.Tensor | None = None) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM), the 3DGS loss (lambda 0.2; NimbusGS uses 0.4).

    ``pred``, ``gt``: ``(H, W, 3)``.  ``mask``: bool ``(H, W)``, True where the pixel counts
    (a view's validity mask); both terms are then means over the valid pixels and
    neither the target's nor the render's colours in invalid pixels reach the loss or its
    gradient (see :func:`nimbus.metrics.masked_pair`).  The caller guarantees at least one valid pixel.
    ``gt_moments``: :func:`loss_target_moments` of this ``gt`` (or None), for a target used at many steps:
    the same loss, bit for bit, in less time.
    """
    # Masked views keep the torch ops: the kernel computes the masked loss as well (to rounding), but
    # the masked-training figures (tests/test_masks.py's occluder run) sit close to their margins
    # and were recorded with these ops.
    if mask is None and train_step.loss_usable(pred, gt, mask):
        return train_step.photometric_loss(pred, gt, lambda_dssim, loss_taps(), SSIM_C1, SSIM_C2,
                                           gt_moments=gt_moments)
    return (1.0 - lambda_dssim) * l1(pred, gt, mask) + lambda_dssim * (1.0 - mean_ssim(pred, gt, mask))


def loss_target_moments(gt: torch.Tensor) -> torch.Tensor | None:
    """What :func:`photometric_loss` can reuse of an unmasked target ``gt`` at every step (its SSIM's filtered
    moments, ``[2, C, H, W]``), or None where the loss would not use it (the torch ops compute that loss)."""
    if not train_step.loss_usable(gt, gt, None):
        return None
    return train_step.target_moments(gt, loss_taps())
