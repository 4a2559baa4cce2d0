"""Full-reference image metrics: the 8-bit round trip, PSNR and SSIM (three named protocols), with validity masks.

Conventions (``shared/notes/evaluation-and-environment.md``):

* Inputs are RGB float images in [0, 1], ``pred`` the rendering and ``gt`` the ground truth,
  either numpy arrays (anything ``numpy.asarray`` accepts) ``(H, W, 3)`` or batches
  ``(B, H, W, 3)``, or torch tensors ``(H, W, 3)`` on any device.
* Numpy inputs are what the benchmark scores: computed in float64 on the CPU, one value per
  image (a float for one image, a ``(B,)`` array for a batch).
* Torch inputs are what training evaluates on its device: computed in the tensor's dtype
  (float32 in training) with the SSIM map the training loss optimises (:func:`ssim_map`; on the
  CPU the loss runs it in a compiled kernel, :mod:`nimbus.kernels.train_step`, equal to rounding), one
  float.  Only the ``"3dgs"`` SSIM protocol is offered there.  Both paths agree to ~1e-6 in
  SSIM and ~1e-5 dB in PSNR; their arithmetic is kept apart because each one's figures
  (results files, regression references) must not change by a bit.
* ``quantize=True`` (the default) first puts both images through the 8-bit round trip of
  :func:`quantize_8bit`, exactly what saving them as PNG does, so scoring in memory and
  scoring saved renders give the same numbers.
* Every value is per image; a dataset's figure is the mean over its views (PSNR is
  averaged in dB, as the field does).

SSIM protocols (11-tap Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2 everywhere):

``"3dgs"`` (default)
    zero 'same' padding, mean over the whole map: the 3DGS / NimbusGS evaluation scripts,
    the paper's numbers and the training loss's SSIM (:func:`ssim_map`).
``"skimage"``
    the 3dgs map with a 5 px border dropped: equals
    ``skimage.metrics.structural_similarity(gt, pred, data_range=1.0, channel_axis=-1,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.
``"dmpix"``
    'valid' convolution with dm_pix's clamping of the variances and covariance:
    ``dm_pix.ssim`` / nerfbaselines.

The protocols differ by ~0.01 on real images, more than the margins between methods,
so every table must name the one it used.

Validity masks (``mask``: bool ``(H, W)``, or ``(B, H, W)`` for numpy batches; True = the
pixel counts; a view's ``masks/`` file): PSNR is the MSE over the valid pixels; SSIM is the
map of both images with their invalid pixels set to 0 (:func:`masked_pair`), averaged over
the valid pixels (kept by the protocol's crop), so for a rectangular mask it equals the SSIM
of that rectangle with the 3dgs protocol.  See :data:`MASK_PROTOCOL`; LPIPS's rule is in
:mod:`nimbus.metrics.lpips`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Callable

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from nimbus.data.images import to_uint8
from nimbus.errors import NimbusError

SSIM_WINDOW = 11     # Gaussian window side (pixels)
SSIM_SIGMA = 1.5     # its standard deviation (pixels)
SSIM_C1 = 0.01**2    # stabilising constants for data range 1
SSIM_C2 = 0.03**2
SSIM_BATCH = 8       # images per numpy SSIM batch: bounds memory (~30 MB per 320x240 image in float64)


@dataclass(frozen=True)
class SSIMProtocol:
    """One way of computing SSIM, named so that tables can say which they used.

    Attributes
    ----------
    name : str
    padding : {"same", "valid"}
        Zero 'same' padding (map has the image's size) or 'valid' windows only.
    crop : int
        Border pixels dropped from each side of the map before averaging.
    clamp_moments : bool
        Clamp the variances to >= float32 eps^2 and |covariance| to <= sqrt(var_x var_y)
        (dm_pix does; it only changes values at rounding level).
    reference : str
        Whose numbers the protocol reproduces.
    """

    name: str
    padding: str
    crop: int
    clamp_moments: bool
    reference: str


SSIM_PROTOCOLS: dict[str, SSIMProtocol] = {
    "3dgs": SSIMProtocol("3dgs", "same", 0, False,
                         "3DGS / NimbusGS evaluation: 11x11 Gaussian (sigma 1.5), zero 'same' padding, full mean"),
    "skimage": SSIMProtocol("skimage", "same", SSIM_WINDOW // 2, False,
                            "skimage structural_similarity(gaussian_weights=True, sigma=1.5, "
                            "use_sample_covariance=False, data_range=1): 5 px border cropped"),
    "dmpix": SSIMProtocol("dmpix", "valid", 0, True,
                          "dm_pix.ssim / nerfbaselines: 11-tap Gaussian (sigma 1.5), 'valid' convolution"),
}
PSNR_PROTOCOL = "per image on [0, 1] after an 8-bit round trip of both images; mean over views"
MASK_PROTOCOL = ("valid pixels only: PSNR = MSE over valid pixels; SSIM = map of both images with invalid "
                 "pixels set to 0, mean over valid pixels; LPIPS = whole image after the prediction's invalid "
                 "pixels are replaced by the ground truth's")


def get_ssim_protocol(name: str) -> SSIMProtocol:
    """The :class:`SSIMProtocol` called ``name`` (NimbusError naming the choices otherwise)."""
    try:
        return SSIM_PROTOCOLS[name]
    except KeyError:
        raise NimbusError(f"unknown SSIM protocol {name!r}; use one of {', '.join(SSIM_PROTOCOLS)}") from None


# --- the 8-bit round trip -------------------------------------------------------------------
def quantize_8bit(image: Any) -> Any:
    """The 8-bit round trip of a float image in [0, 1]: ``round(255 clip(x, 0, 1)) / 255``.

    Parameters
    ----------
    image : ndarray or Tensor, any shape, float in [0, 1]

    Returns
    -------
    ndarray float32, or Tensor of ``image``'s dtype and device
        Multiples of 1/255 in [0, 1].  Numpy: rounds half up and maps NaN to 0, exactly as
        :func:`nimbus.data.images.to_uint8` stores a PNG.  Torch (training's evaluation):
        ``torch.round`` (half to even) and NaN stays NaN; saved as PNG, the result reads
        back unchanged.  The two differ only for values exactly halfway between two steps.
    """
    if isinstance(image, torch.Tensor):
        return torch.round(image.clamp(0, 1) * 255.0) / 255.0
    return to_uint8(image).astype(np.float32) / np.float32(255.0)


# --- input handling -------------------------------------------------------------------------
def as_batches(pred: Any, gt: Any, quantize: bool) -> tuple[np.ndarray, np.ndarray, bool]:
    """Both numpy inputs as float32 (B, H, W, 3) batches, checked, 8-bit round-tripped when ``quantize``.

    Returns ``(pred, gt, single)``; ``single``: they were one (H, W, 3) image each (then a
    metric returns a float rather than a (B,) array).
    """
    a = np.asarray(pred, dtype=np.float32)
    b = np.asarray(gt, dtype=np.float32)
    _check_shapes(a.shape, b.shape, (3, 4))
    single = a.ndim == 3
    if single:
        a, b = a[None], b[None]
    if quantize:
        a, b = quantize_8bit(a), quantize_8bit(b)
    return a, b, single


def _check_shapes(a: tuple[int, ...], b: tuple[int, ...], ndims: tuple[int, ...]) -> None:
    if a != b:
        raise NimbusError(f"prediction and ground truth differ in shape: {a} vs {b}; "
                          "render at the ground truth's resolution")
    if len(a) not in ndims or a[-1] != 3:
        shapes = " or ".join(("(H, W, 3)", "(B, H, W, 3)")[:len(ndims)])
        raise NimbusError(f"images must be {shapes} RGB arrays, got shape {a}")


def _torch_pair(pred: torch.Tensor, gt: torch.Tensor, quantize: bool,
                mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Checks of the torch path: one (H, W, 3) image each, a mask of its size; the 8-bit round trip."""
    _check_shapes(tuple(pred.shape), tuple(gt.shape), (3,))
    if mask is not None and tuple(mask.shape) != tuple(pred.shape[:2]):
        raise NimbusError(f"mask shape {tuple(mask.shape)} does not match the image's {tuple(pred.shape[:2])}")
    if quantize:
        pred, gt = quantize_8bit(pred), quantize_8bit(gt)
    return pred, gt


def _result(values: np.ndarray, single: bool):
    return float(values[0]) if single else values


def mask_batch(mask: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    """``mask`` as a bool (B, H, W) batch for images of (B, H, W, 3) ``shape``, or None.

    Raises
    ------
    NimbusError
        The mask's shape does not match, or a mask keeps no pixel.
    """
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.ndim == 2:
        m = m[None]
    if m.shape != shape[:3]:
        raise NimbusError(f"mask shape {np.shape(mask)} does not match the images' {shape[:3]} (B, H, W); give "
                          "one bool (H, W) mask of the image's size per image")
    m = m.astype(bool)
    if not m.reshape(len(m), -1).any(axis=1).all():
        raise NimbusError("a mask keeps no pixel (True / non-zero = the pixel counts); such a view cannot be scored")
    return m


# --- PSNR ----------------------------------------------------------------------------------
def peak_signal_noise_ratio(pred: Any, gt: Any, *, quantize: bool = True, mask: Any = None):
    """Peak signal-to-noise ratio in dB, per image (peak 1).

    Parameters
    ----------
    pred, gt : ndarray (H, W, 3) or (B, H, W, 3), or Tensor (H, W, 3); float in [0, 1]
        See the module docstring for the numpy and torch paths.
    quantize : bool
        Apply the 8-bit round trip to both first (the benchmark's convention).
    mask : bool ndarray (H, W) or (B, H, W), or bool Tensor (H, W) on the images' device, optional
        Validity mask: the MSE is over the True pixels only (at least one per image).

    Returns
    -------
    float, or ndarray (B,) float64 for a numpy batch
        ``-10 log10(MSE)``; typically 10-50 dB, higher is better; ``inf`` for identical images.
        The torch path takes the logarithm in float32 (as training always logged it).
    """
    if isinstance(pred, torch.Tensor):
        a, b = _torch_pair(pred, gt, quantize, mask)
        a, b = a.detach().float(), b.detach().float()
        err = (a - b) ** 2
        if mask is None:
            mse = float(err.mean())
        else:
            w = mask.to(err.dtype)[..., None]
            mse = float((err * w).sum() / (w.sum() * err.shape[-1]))
        return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
    a, b, single = as_batches(pred, gt, quantize)
    m = mask_batch(mask, a.shape)
    err = ((a.astype(np.float64) - b) ** 2).reshape(len(a), -1, 3)
    if m is None:
        mse = err.reshape(len(a), -1).mean(axis=1)
    else:
        w = m.reshape(len(a), -1, 1)
        mse = (err * w).sum(axis=(1, 2)) / (w.sum(axis=(1, 2)) * 3)
    with np.errstate(divide="ignore"):
        return _result(-10.0 * np.log10(mse), single)


# --- SSIM: one formula, two filters ------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _gaussian_taps() -> np.ndarray:
    """The 1-D window: ``SSIM_WINDOW`` float64 taps of a Gaussian with ``SSIM_SIGMA``, summing to 1."""
    x = np.arange(SSIM_WINDOW, dtype=np.float64) - (SSIM_WINDOW - 1) / 2
    g = np.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return g / g.sum()


def _ssim_from_moments(filt: Callable, x, y, clamp: Callable | None = None):
    """The SSIM map of images ``x``, ``y`` (numpy arrays or torch tensors) given the window filter ``filt``.

    Shared by the training loss, the torch metric and the numpy metric.  The order of the
    operations is that of the training loss since it was written: autograd accumulates
    gradients in the order the graph was built, so reordering would change the loss's
    gradients in the last bits.  ``clamp(sxx, syy, sxy)`` optionally adjusts the moments.
    """
    mu_x, mu_y = filt(x), filt(y)
    sxx = filt(x * x) - mu_x**2
    syy = filt(y * y) - mu_y**2
    sxy = filt(x * y) - mu_x * mu_y
    if clamp is not None:
        sxx, syy, sxy = clamp(sxx, syy, sxy)
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2)
    return num / den


@functools.lru_cache(maxsize=1)
def loss_taps() -> torch.Tensor:
    """The 1-D window of the torch SSIM (training loss and torch metric): float64 ``[SSIM_WINDOW]``.

    The taps are computed as the training loss always computed them, ``exp(-x^2 / (2 sigma^2))``
    in torch: :func:`_gaussian_taps`' ``exp(-(x / sigma)^2 / 2)`` differs by 1 ulp in the two
    outermost float64 taps, which would change the loss's float64 gradients (not its float32
    ones) in the last bits.  Each path keeps its own arithmetic so no figure changes.
    """
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - (SSIM_WINDOW - 1) / 2
    g = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return g / g.sum()


@functools.lru_cache(maxsize=8)
def _gaussian_window(device_str: str, dtype: torch.dtype) -> torch.Tensor:
    """The 2-D window (outer product of :func:`loss_taps`) for torch's conv2d."""
    g = loss_taps()
    return torch.outer(g, g).to(device=torch.device(device_str), dtype=dtype)


def ssim_map(a: torch.Tensor, b: torch.Tensor, padding: str = "same") -> torch.Tensor:
    """Per-pixel SSIM of two torch images, per channel; differentiable (the training loss uses it).

    Parameters
    ----------
    a, b : Tensor (H, W, C) or (B, H, W, C), float in [0, 1]
    padding : {"same", "valid"}
        ``"same"`` zero-pads (the 3DGS / NimbusGS protocol: the map has the image's size);
        ``"valid"`` keeps only windows fully inside the image (dm_pix / nerfbaselines).

    Returns
    -------
    Tensor (B, C, H', W')
        SSIM in [-1, 1] per pixel and channel, 1 where the images are equal.
    """
    if a.shape != b.shape:
        raise ValueError(f"ssim: shapes differ {tuple(a.shape)} vs {tuple(b.shape)}")
    x = a if a.dim() == 4 else a[None]
    y = b if b.dim() == 4 else b[None]
    x = x.permute(0, 3, 1, 2)
    y = y.permute(0, 3, 1, 2)
    c = x.shape[1]
    w = _gaussian_window(str(x.device), x.dtype).expand(c, 1, SSIM_WINDOW, SSIM_WINDOW)
    pad = SSIM_WINDOW // 2 if padding == "same" else 0
    return _ssim_from_moments(lambda t: F.conv2d(t, w, padding=pad, groups=c), x, y)


def masked_pair(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Both torch images with their invalid pixels set to 0, and the mask as a float ``(H, W, 1)`` weight.

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


def mean_ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of torch images with the 3dgs protocol; differentiable (the training loss's SSIM term).

    Parameters
    ----------
    a, b : Tensor (H, W, 3) or (B, H, W, 3), float in [0, 1]
    mask : bool Tensor (H, W), optional
        The SSIM map of the images with the invalid pixels zeroed (:func:`masked_pair`),
        averaged over the valid pixels only (shared by every image of a batch).

    Returns
    -------
    Tensor, 0-d
        At most 1 (identical images).
    """
    a, b, w = masked_pair(a, b, mask)
    m = ssim_map(a, b)
    if w is None:
        return m.mean()
    return (m * w[..., 0]).sum() / (w.sum() * m.shape[0] * m.shape[1])  # valid pixels x batch x channels


def _filter(maps: np.ndarray, valid: bool) -> np.ndarray:
    """Separable 11x11 Gaussian filter of (N, H, W) float64 maps: zero 'same' padding or 'valid'.

    OpenCV's separable filter in float64 (exact to ~1e-15; float32 moments would lose ~4e-5
    of SSIM to cancellation in E[x^2] - E[x]^2), one map at a time: 11 multiply-adds per
    output and pass, ~4x faster on CPU than the banded matrix product it replaced
    (``tools/speed/metrics.py``).  'valid' is the 'same' map without its
    ``SSIM_WINDOW // 2`` border, where no window reaches into the padding.
    """
    g = _gaussian_taps()
    out = np.empty_like(maps)
    for i, m in enumerate(maps):
        out[i] = cv2.sepFilter2D(m, cv2.CV_64F, g, g, borderType=cv2.BORDER_CONSTANT)
    if valid:
        half = SSIM_WINDOW // 2
        out = out[:, half:-half, half:-half]
    return out


def _clamp_moments(sxx: np.ndarray, syy: np.ndarray, sxy: np.ndarray) -> tuple[np.ndarray, ...]:
    """dm_pix's clamping: variances >= float32 eps^2, |covariance| <= sqrt(var_x var_y)."""
    eps2 = float(np.finfo(np.float32).eps) ** 2
    sxx, syy = np.maximum(sxx, eps2), np.maximum(syy, eps2)
    return sxx, syy, np.sign(sxy) * np.minimum(np.sqrt(sxx * syy), np.abs(sxy))


def _ssim_batch(a: np.ndarray, b: np.ndarray, proto: SSIMProtocol, mask: np.ndarray | None = None) -> np.ndarray:
    """Mean SSIM of each pair of a (B, H, W, C) float32 batch -> (B,) float64 (over ``mask``'s valid pixels)."""
    n, h, w, c = a.shape
    if mask is not None:  # invalid pixels enter no window: zero in both images, like padding at a crop's edge
        a, b = a * mask[..., None], b * mask[..., None]
    x = a.astype(np.float64).transpose(0, 3, 1, 2).reshape(n * c, h, w)
    y = b.astype(np.float64).transpose(0, 3, 1, 2).reshape(n * c, h, w)
    valid = proto.padding == "valid"
    m = _ssim_from_moments(lambda t: _filter(t, valid), x, y, _clamp_moments if proto.clamp_moments else None)
    if proto.crop:
        k = proto.crop
        m = m[:, k:-k, k:-k]
    if mask is None:
        return m.reshape(n, -1).mean(axis=1)
    k = (SSIM_WINDOW // 2 if valid else 0) + proto.crop  # the map's border cut, on the mask
    wts = mask[:, k:h - k, k:w - k].astype(np.float64)
    counts = wts.reshape(n, -1).sum(axis=1)
    if not counts.all():
        raise NimbusError(f"a mask keeps no pixel inside the {k} px border that the {proto.name} SSIM protocol "
                          "drops; score with --ssim 3dgs or use a larger valid region")
    return (m.reshape(n, c, *wts.shape[1:]) * wts[:, None]).reshape(n, -1).sum(axis=1) / (counts * c)


def _check_ssim_size(shape: tuple[int, ...]) -> None:
    if min(shape[1], shape[2]) < SSIM_WINDOW:
        raise NimbusError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got "
                          f"{shape[2]}x{shape[1]}")


def structural_similarity(pred: Any, gt: Any, *, protocol: str = "3dgs", quantize: bool = True, mask: Any = None):
    """Structural similarity, per image, with a named protocol.

    Parameters
    ----------
    pred, gt : ndarray (H, W, 3) or (B, H, W, 3), or Tensor (H, W, 3); float in [0, 1]
        Numpy: H and W at least 11 (the window).  See the module docstring for the numpy and torch paths.
    protocol : {"3dgs", "skimage", "dmpix"}
        See the module docstring; ``"3dgs"`` is the paper's and the only one for torch tensors.
    quantize : bool
        Apply the 8-bit round trip to both first.
    mask : bool ndarray (H, W) or (B, H, W), or bool Tensor (H, W) on the images' device, optional
        Validity mask: the map of both images with the False pixels set to 0, averaged over the
        True pixels (see the module docstring).

    Returns
    -------
    float, or ndarray (B,) float64 for a numpy batch
        Mean SSIM over pixels and channels; at most 1 (identical images), higher is better.
    """
    proto = get_ssim_protocol(protocol)
    if isinstance(pred, torch.Tensor):
        if proto.name != "3dgs":
            raise NimbusError(f"SSIM of torch tensors uses the 3dgs protocol only, not {proto.name!r}; "
                              "pass numpy arrays for the others")
        a, b = _torch_pair(pred, gt, quantize, mask)  # any size: the zero-padded map needs no full window
        return float(mean_ssim(a, b, mask))
    a, b, single = as_batches(pred, gt, quantize)
    _check_ssim_size(a.shape)
    m = mask_batch(mask, a.shape)
    out = np.concatenate([_ssim_batch(a[s:s + SSIM_BATCH], b[s:s + SSIM_BATCH], proto,
                                      None if m is None else m[s:s + SSIM_BATCH])
                          for s in range(0, len(a), SSIM_BATCH)])
    return _result(out, single)
