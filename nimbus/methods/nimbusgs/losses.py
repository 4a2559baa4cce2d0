"""NimbusGS regularisers: the dark-channel prior on the clean render (L_DCP) and the training objective.

L_TV lives with the extinction field (:meth:`nimbus.methods.nimbusgs.scattering.ExtinctionGrid.tv`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from nimbus.losses import photometric_loss
from nimbus.methods.nimbusgs.airlight import window_min


def soft_dark_channel(image: Tensor, patch: int, temperature: float) -> Tensor:
    """Differentiable dark channel ``[H, W, 3] -> [H, W]``.

    A soft minimum over the colour channels (softmax(-c / temperature)-weighted mean,
    which stays within [min, max] of the channels; temperature 0 gives the hard
    minimum), then a ``patch`` x ``patch`` minimum filter (He et al.; released code:
    temperature 0.1, patch 15).
    """
    if temperature > 0:
        w = torch.softmax(-image / temperature, dim=-1)
        m = (w * image).sum(dim=-1)
    else:
        m = image.min(dim=-1).values
    return window_min(m, patch)


DCP_FORMS = ("l1", "squared")


def dcp_loss(clean: Tensor, patch: int, temperature: float, form: str = "l1", mask: Tensor | None = None) -> Tensor:
    """The dark-channel prior on the clean render.

    ``form="l1"``: ||DCP(I_hat)||_1 as a per-pixel mean (paper Eq. 12); ``"squared"``:
    mean(DCP(I_hat))^2 (the authors' released code), whose pull fades as the dark
    channel approaches 0.  ``mask`` (bool ``[H, W]``) keeps the prior to those pixels;
    the mean is still over all pixels, so a full mask is the paper's loss.
    """
    dark = soft_dark_channel(clean, patch, temperature).abs()
    if mask is not None:
        dark = dark * mask.to(dark.dtype)
    dark = dark.mean()
    return dark * dark if form == "squared" else dark


def stage_loss(pred: Tensor, target: Tensor, lambda_r: float, mask: Tensor | None = None,
               target_moments: Tensor | None = None) -> Tensor:
    """(1 - lambda_r) ||I_in - pred||_1 + lambda_r (1 - SSIM(I_in, pred)) (paper Eqs. 11 and 14).

    ``mask`` (bool ``[H, W]``): the view's validity mask; both terms are means over its valid
    pixels (:func:`nimbus.losses.photometric_loss`).  ``target_moments``: the target's
    :func:`nimbus.losses.loss_target_moments`, for a target used at many steps (the same loss).
    """
    return photometric_loss(pred, target, lambda_r, mask, target_moments)
