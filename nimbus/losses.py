"""Differentiable image losses and the training-time image metrics.

Images are torch tensors (H, W, 3) or (B, H, W, 3) in [0, 1].
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@functools.lru_cache(maxsize=8)
def _gaussian_window(size: int, sigma: float, device_str: str, dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return torch.outer(g, g).to(device=torch.device(device_str), dtype=dtype)


def ssim_map(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5,
             padding: str = "same") -> torch.Tensor:
    """Per-pixel SSIM of two images (H, W, C) or (B, H, W, C), per channel, shape (B, C, H', W').

    ``padding="same"`` zero-pads (the 3DGS / NimbusGS protocol: the map has the
    image's size); ``"valid"`` keeps only windows fully inside the image
    (dm_pix / nerfbaselines).  Constants C1 = 0.01^2, C2 = 0.03^2 for data range 1.
    """
    if a.shape != b.shape:
        raise ValueError(f"ssim: shapes differ {tuple(a.shape)} vs {tuple(b.shape)}")
    x = a if a.dim() == 4 else a[None]
    y = b if b.dim() == 4 else b[None]
    x = x.permute(0, 3, 1, 2)
    y = y.permute(0, 3, 1, 2)
    c = x.shape[1]
    w = _gaussian_window(window, sigma, str(x.device), x.dtype).expand(c, 1, window, window)
    pad = window // 2 if padding == "same" else 0

    def filt(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, w, padding=pad, groups=c)

    mu_x, mu_y = filt(x), filt(y)
    sxx = filt(x * x) - mu_x**2
    syy = filt(y * y) - mu_y**2
    sxy = filt(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2)
    return num / den


def masked_pair(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Both images with their invalid pixels set to 0, and the mask as a float ``(H, W, 1)`` weight.

    Zeroing both images (rather than weighting the residual) keeps the colours of the
    invalid pixels out of every SSIM window that reaches into them: the map then sees
    exactly the zero padding it would see at the edge of a crop, so for a rectangular
    mask the masked losses and metrics equal the plain ones on that rectangle.  The
    gradient with respect to an invalid pixel of ``a`` is 0.  ``mask`` None: the
    images are returned as they are (no extra work for views without masks).
    """
    if mask is None:
        return a, b, None
    if mask.shape != a.shape[-3:-1]:
        raise ValueError(f"mask shape {tuple(mask.shape)} does not match the image's {tuple(a.shape[-3:-1])}")
    w = mask.to(a.dtype)[..., None]
    return a * w, b * w, w


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM with the 3DGS training protocol (11x11 Gaussian window, sigma 1.5, zero padding).

    ``mask`` (bool ``(H, W)``, True = the pixel counts): the SSIM map of the images with the
    invalid pixels zeroed (:func:`masked_pair`), averaged over the valid pixels only.
    """
    a, b, w = masked_pair(a, b, mask)
    m = ssim_map(a, b)
    if w is None:
        return m.mean()
    return (m * w[..., 0]).sum() / (w.sum() * m.shape[0] * m.shape[1])  # valid pixels x batch x channels


def l1(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute difference, over the valid pixels when ``mask`` (bool ``(H, W)``) is given."""
    if mask is None:
        return (a - b).abs().mean()
    a, b, w = masked_pair(a, b, mask)
    return (a - b).abs().sum() / (w.expand_as(a).sum())


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float,
                     mask: torch.Tensor | None = None) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM), the 3DGS loss (lambda 0.2; NimbusGS uses 0.4).

    ``pred``, ``gt``: ``(H, W, 3)``.  ``mask``: bool ``(H, W)``, True where the pixel counts
    (a view's validity mask); both terms are then means over the valid pixels and
    neither the target's nor the render's colours in invalid pixels reach the loss or its
    gradient (see :func:`masked_pair`).  The caller guarantees at least one valid pixel.
    """
    return (1.0 - lambda_dssim) * l1(pred, gt, mask) + lambda_dssim * (1.0 - ssim(pred, gt, mask))


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB for images in [0, 1] (no quantisation; the benchmark's PSNR quantises to 8 bits first).

    ``mask`` (bool ``(H, W)``): the mean squared error over the valid pixels only.
    """
    a, b = a.detach().float(), b.detach().float()
    err = (a - b) ** 2
    if mask is None:
        mse = float(err.mean())
    else:
        w = mask.to(err.dtype)[..., None]
        mse = float((err * w).sum() / (w.sum() * err.shape[-1]))
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
