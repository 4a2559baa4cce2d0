"""Image-quality metrics of the benchmark: PSNR, SSIM (three named protocols) and LPIPS.

Conventions (``shared/notes/evaluation-and-environment.md``):

* Inputs are RGB float images in [0, 1], ``(H, W, 3)`` or batches ``(B, H, W, 3)``
  (numpy arrays, or anything ``numpy.asarray`` accepts).  ``pred`` is the rendering,
  ``gt`` the ground truth.
* Both images are put through an 8-bit round trip first (``round(255 x) / 255``, after
  clipping to [0, 1]; NaN becomes 0), exactly what saving them as PNG does, so scoring
  in memory and scoring saved renders give the same numbers.  ``quantize=False`` skips it.
* Every value is per image; a dataset's figure is the mean over its views (PSNR is
  averaged in dB, as the field does).

SSIM protocols (11-tap Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2 everywhere):

``"3dgs"`` (default)
    zero 'same' padding, mean over the whole map: the 3DGS / NimbusGS evaluation scripts
    and the paper's numbers (:func:`nimbus.losses.ssim_map`, the trainers' SSIM, computed
    in float64 here; the tests check they agree).
``"skimage"``
    the 3dgs map with a 5 px border dropped: equals
    ``skimage.metrics.structural_similarity(gt, pred, data_range=1.0, channel_axis=-1,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.
``"dmpix"``
    'valid' convolution with dm_pix's clamping of the variances and covariance:
    ``dm_pix.ssim`` / nerfbaselines.

The protocols differ by ~0.01 on real images, more than the margins between methods,
so every table must name the one it used.

Validity masks (``mask``: bool ``(H, W)`` or ``(B, H, W)``, True = the pixel counts; a
view's ``masks/`` file): PSNR is the MSE over the valid pixels; SSIM is the map of both
images with their invalid pixels set to 0, averaged over the valid pixels (kept by the
protocol's crop), so for a rectangular mask it equals the SSIM of that rectangle with the
3dgs protocol; LPIPS is of whole images after the prediction's invalid pixels are
replaced by the ground truth's (the peers' practice: both images on the same background;
the distance is then diluted by the invalid fraction).  See :data:`MASK_PROTOCOL`.
"""

from __future__ import annotations

import functools
import hashlib
import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from benchmark.lpips import LPIPS_NETS, LPIPSNetwork, min_input_size, unit_normalize
from benchmark.lpips_onnx import OnnxTrunk
from benchmark.weights import SETUP_COMMAND, WeightsMissing, load_weights, weights_info
from nimbus.data.images import to_uint8
from nimbus.errors import NimbusError
from nimbus.losses import SSIM_C1, SSIM_C2

SSIM_WINDOW = 11     # Gaussian window side (pixels)
SSIM_SIGMA = 1.5     # its standard deviation (pixels)
SSIM_BATCH = 8       # images per SSIM batch: bounds memory (~30 MB per 320x240 image in float64)
LPIPS_BATCH = 4      # image pairs per LPIPS batch: VGG on 320x240 needs ~0.1 GB per pair
LPIPS_GT_CACHE_MB = 1024  # memory for cached ground-truth LPIPS features (MiB; see LPIPS)
LPIPS_BACKENDS = ("auto", "onnxruntime", "torch")
#: What ``backend="auto"`` runs each trunk with on the CPU: onnxruntime where it took less CPU time
#: (VGG: ~1.2x less), torch where it did not (AlexNet: ~10% more with onnxruntime); see
#: benchmark/bench_metrics.py.  Other devices use torch.
LPIPS_CPU_BACKEND = {"vgg": "onnxruntime", "alex": "torch"}


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


# --- input handling ----------------------------------------------------------------------
def quantize_8bit(img: np.ndarray) -> np.ndarray:
    """The 8-bit round trip: ``round(255 clip(x, 0, 1)) / 255`` as float32 (NaN -> 0, as a PNG would hold it)."""
    return to_uint8(img).astype(np.float32) / np.float32(255.0)


def _pair(pred: Any, gt: Any, quantize: bool) -> tuple[np.ndarray, np.ndarray, bool]:
    """Both inputs as float32 (B, H, W, 3) batches; ``single`` when they were one (H, W, 3) image each."""
    a = np.asarray(pred, dtype=np.float32)
    b = np.asarray(gt, dtype=np.float32)
    if a.shape != b.shape:
        raise NimbusError(f"prediction and ground truth differ in shape: {a.shape} vs {b.shape}; "
                          "render at the ground truth's resolution")
    if a.ndim not in (3, 4) or a.shape[-1] != 3:
        raise NimbusError(f"images must be (H, W, 3) or (B, H, W, 3) RGB arrays, got shape {a.shape}")
    single = a.ndim == 3
    if single:
        a, b = a[None], b[None]
    if quantize:
        a, b = quantize_8bit(a), quantize_8bit(b)
    return a, b, single


def _result(values: np.ndarray, single: bool):
    return float(values[0]) if single else values


def _mask_batch(mask: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    """``mask`` as a bool (B, H, W) batch for images of (B, H, W, 3) ``shape``, or None."""
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


# --- PSNR --------------------------------------------------------------------------------
def psnr(pred: Any, gt: Any, quantize: bool = True, mask: Any = None):
    """Peak signal-to-noise ratio in dB, per image (peak 1).

    Parameters
    ----------
    pred, gt : array, (H, W, 3) or (B, H, W, 3), float in [0, 1]
    quantize : bool
        Apply the 8-bit round trip to both first (the benchmark's convention).
    mask : array of bool, (H, W) or (B, H, W), optional
        Validity mask: the MSE is over the True pixels only.

    Returns
    -------
    float or ndarray (B,) float64
        ``-10 log10(MSE)``; typically 10-50 dB, higher is better; ``inf`` for identical images.
    """
    a, b, single = _pair(pred, gt, quantize)
    m = _mask_batch(mask, a.shape)
    err = ((a.astype(np.float64) - b) ** 2).reshape(len(a), -1, 3)
    if m is None:
        mse = err.reshape(len(a), -1).mean(axis=1)
    else:
        w = m.reshape(len(a), -1, 1)
        mse = (err * w).sum(axis=(1, 2)) / (w.sum(axis=(1, 2)) * 3)
    with np.errstate(divide="ignore"):
        return _result(-10.0 * np.log10(mse), single)


# --- SSIM --------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _gaussian_taps() -> np.ndarray:
    x = np.arange(SSIM_WINDOW, dtype=np.float64) - (SSIM_WINDOW - 1) / 2
    g = np.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return g / g.sum()


def _filter(maps: np.ndarray, valid: bool) -> np.ndarray:
    """Separable 11x11 Gaussian filter of (N, H, W) float64 maps: zero 'same' padding or 'valid'.

    OpenCV's separable filter in float64 (exact to ~1e-15; float32 moments would lose ~4e-5
    of SSIM to cancellation in E[x^2] - E[x]^2), one map at a time: 11 multiply-adds per
    output and pass, ~4x faster on CPU than the banded matrix product it replaced
    (``benchmark/bench_metrics.py``).  'valid' is the 'same' map without its
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


def _ssim_batch(a: np.ndarray, b: np.ndarray, proto: SSIMProtocol, mask: np.ndarray | None = None) -> np.ndarray:
    """Mean SSIM of each pair of a (B, H, W, C) float32 batch -> (B,) float64 (over ``mask``'s valid pixels)."""
    n, h, w, c = a.shape
    if mask is not None:  # invalid pixels enter no window: zero in both images, like padding at a crop's edge
        a, b = a * mask[..., None], b * mask[..., None]
    x = a.astype(np.float64).transpose(0, 3, 1, 2).reshape(n * c, h, w)
    y = b.astype(np.float64).transpose(0, 3, 1, 2).reshape(n * c, h, w)
    valid = proto.padding == "valid"
    mu_x, mu_y, exx, eyy, exy = (_filter(m, valid) for m in (x, y, x * x, y * y, x * y))
    sxx = exx - mu_x**2
    syy = eyy - mu_y**2
    sxy = exy - mu_x * mu_y
    if proto.clamp_moments:
        eps2 = float(np.finfo(np.float32).eps) ** 2
        sxx, syy = np.maximum(sxx, eps2), np.maximum(syy, eps2)
        sxy = np.sign(sxy) * np.minimum(np.sqrt(sxx * syy), np.abs(sxy))
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    m = num / ((mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2))
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


def ssim(pred: Any, gt: Any, protocol: str = "3dgs", quantize: bool = True, mask: Any = None):
    """Structural similarity, per image, with a named protocol.

    Parameters
    ----------
    pred, gt : array, (H, W, 3) or (B, H, W, 3), float in [0, 1]
        H and W at least 11 (the window).
    protocol : {"3dgs", "skimage", "dmpix"}
        See the module docstring; ``"3dgs"`` is the paper's.
    quantize : bool
        Apply the 8-bit round trip to both first.
    mask : array of bool, (H, W) or (B, H, W), optional
        Validity mask: the map of both images with the False pixels set to 0, averaged over the
        True pixels (see the module docstring).

    Returns
    -------
    float or ndarray (B,) float64
        Mean SSIM over pixels and channels; at most 1 (identical images), higher is better.
    """
    proto = get_ssim_protocol(protocol)
    a, b, single = _pair(pred, gt, quantize)
    _check_ssim_size(a.shape)
    m = _mask_batch(mask, a.shape)
    out = np.concatenate([_ssim_batch(a[s:s + SSIM_BATCH], b[s:s + SSIM_BATCH], proto,
                                      None if m is None else m[s:s + SSIM_BATCH])
                          for s in range(0, len(a), SSIM_BATCH)])
    return _result(out, single)


def get_ssim_protocol(name: str) -> SSIMProtocol:
    """The :class:`SSIMProtocol` called ``name`` (NimbusError naming the choices otherwise)."""
    try:
        return SSIM_PROTOCOLS[name]
    except KeyError:
        raise NimbusError(f"unknown SSIM protocol {name!r}; use one of {', '.join(SSIM_PROTOCOLS)}") from None


def _check_ssim_size(shape: tuple[int, ...]) -> None:
    if min(shape[1], shape[2]) < SSIM_WINDOW:
        raise NimbusError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got "
                          f"{shape[2]}x{shape[1]}")


# --- LPIPS -------------------------------------------------------------------------------
class LPIPS:
    """Learned perceptual image patch similarity (LPIPS v0.1), callable on images or batches.

    Parameters
    ----------
    net : {"vgg", "alex"}
        Trunk; ``"vgg"`` is the paper's (and 3DGS's) evaluation, ``"alex"`` nerfbaselines' default.
    device : str or torch.device, optional
        Default: CUDA when available, else CPU.
    state_dict : dict, optional
        Weights in :class:`benchmark.lpips.LPIPSNetwork`'s layout; default: the cache written by
        ``nimbus-bench setup-weights``.  Tests pass random weights.
    batch_size : int
        Image pairs per forward pass (bounds memory; default ``LPIPS_BATCH``).
    backend : {"auto", "onnxruntime", "torch"}
        What runs the trunk.  ``auto`` (default): on the CPU, :data:`LPIPS_CPU_BACKEND`
        (onnxruntime for VGG, :mod:`benchmark.lpips_onnx`; torch for AlexNet); torch on
        other devices.  Both give the same values to ~1e-7.
    gt_cache_mb : float
        Memory budget (MiB) for the ground truth's features, keyed by the image's content:
        scoring several methods against the same views runs the trunk once per view, not
        once per method.  The cache fills until the budget is reached and then keeps what
        it has (a sequential scan would otherwise evict every entry before its reuse).
        0 disables it.  VGG on 320 x 240 needs ~38 MiB per view, AlexNet ~3 MiB.

    Raises
    ------
    WeightsMissing
        (a NimbusError) when the weights are not set up; the message gives the command.

    Examples
    --------
    >>> lp = LPIPS("vgg")                      # doctest: +SKIP
    >>> lp(pred, gt)                           # (H, W, 3) -> float; (B, H, W, 3) -> (B,)  # doctest: +SKIP
    """

    def __init__(self, net: str = "vgg", device: str | torch.device | None = None,
                 state_dict: dict[str, torch.Tensor] | None = None, batch_size: int = LPIPS_BATCH,
                 backend: str = "auto", gt_cache_mb: float = LPIPS_GT_CACHE_MB) -> None:
        if net not in LPIPS_NETS:
            raise NimbusError(f"unknown LPIPS network {net!r}; use one of {', '.join(LPIPS_NETS)}")
        if backend not in LPIPS_BACKENDS:
            raise NimbusError(f"unknown LPIPS backend {backend!r}; use one of {', '.join(LPIPS_BACKENDS)}")
        if state_dict is None:
            state_dict = load_weights(net)
            self.weights = weights_info(net)
        else:
            self.weights = {"package": "custom state_dict"}
        self.net = net
        self.device = torch.device(device) if device is not None else torch.device(
            "cuda" if torch.cuda.is_available() else "cpu")
        self.batch_size = max(1, int(batch_size))
        self.network = LPIPSNetwork(net)
        self.network.load_state_dict(state_dict)
        # channels-last convolutions run ~15% faster on CPU (oneDNN); the inputs, permuted
        # from (B, H, W, 3) arrays, already have that layout.
        self.network.eval().to(self.device, memory_format=torch.channels_last)
        if backend == "auto":
            backend = LPIPS_CPU_BACKEND[net] if self.device.type == "cpu" else "torch"
        if backend == "onnxruntime" and self.device.type != "cpu":
            raise NimbusError(f"the onnxruntime LPIPS backend runs on the CPU only; use backend='torch' "
                              f"for device {self.device}")
        self.backend = backend
        self._trunk = OnnxTrunk(net, state_dict) if backend == "onnxruntime" else None
        self.gt_cache_bytes = int(max(0.0, gt_cache_mb) * 2**20)
        self._gt_cache: dict[bytes, list[torch.Tensor]] = {}
        self._gt_cache_used = 0

    @property
    def name(self) -> str:
        """Protocol name for tables and JSON, e.g. ``"lpips-vgg-v0.1"``."""
        return f"lpips-{self.net}-v0.1"

    @property
    def cached_views(self) -> int:
        """Ground-truth images whose features are in the cache."""
        return len(self._gt_cache)

    def __call__(self, pred: Any, gt: Any, quantize: bool = True):
        """LPIPS distance, per image pair.

        Parameters
        ----------
        pred, gt : array, (H, W, 3) or (B, H, W, 3), float in [0, 1]
            At least ``min_input_size(net)`` pixels on each side (16 for VGG, 31 for AlexNet).
        quantize : bool
            Apply the 8-bit round trip to both first.

        Returns
        -------
        float or ndarray (B,) float64
            >= 0 (0 for identical images); typically 0-0.7, lower is better.
        """
        a, b, single = _pair(pred, gt, quantize)
        need = min_input_size(self.net)
        if min(a.shape[1], a.shape[2]) < need:
            raise NimbusError(f"LPIPS-{self.net} needs images of at least {need}x{need} pixels, got "
                              f"{a.shape[2]}x{a.shape[1]}")
        out = np.empty(len(a), np.float64)
        with torch.inference_mode():
            for s in range(0, len(a), self.batch_size):
                fa, fb = self._pair_features(a[s:s + self.batch_size], b[s:s + self.batch_size])
                out[s:s + len(fa[0])] = self.network.distance(fa, fb).double().cpu().numpy()
        return _result(out, single)

    def _pair_features(self, a: np.ndarray, b: np.ndarray) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Unit-normalised tapped features of a (n, H, W, 3) prediction batch and its ground truth.

        The trunk runs once on the predictions and the ground-truth images not in the cache.
        """
        n = len(a)
        keys = [_image_key(g) for g in b] if self.gt_cache_bytes else [None] * n
        todo = [i for i, k in enumerate(keys) if k not in self._gt_cache]
        feats = self._features(np.concatenate([a, b[todo]]) if todo else a)
        fa = [f[:n] for f in feats]
        new = {i: [f[n + j] for f in feats] for j, i in enumerate(todo)}
        for i in todo:
            self._remember(keys[i], new[i])
        if len(todo) == n:  # nothing came from the cache
            return fa, [f[n:] for f in feats]
        per_view = [new[i] if i in new else self._gt_cache[keys[i]] for i in range(n)]
        fb = [torch.stack([v[k] for v in per_view]) for k in range(len(feats))]
        return fa, fb

    def _features(self, x: np.ndarray) -> list[torch.Tensor]:
        """:meth:`LPIPSNetwork.features` of a (B, H, W, 3) float32 batch, on the chosen backend."""
        t = torch.from_numpy(x).permute(0, 3, 1, 2).to(self.device)
        if self._trunk is None:
            return self.network.features(t)
        raw = self._trunk(self.network.normalize_input(t).contiguous().numpy())
        return [unit_normalize(torch.from_numpy(r)) for r in raw]

    def _remember(self, key: bytes | None, feats: list[torch.Tensor]) -> None:
        if key is None or key in self._gt_cache:  # the same image twice in one batch
            return
        size = sum(f.numel() * f.element_size() for f in feats)
        if self._gt_cache_used + size <= self.gt_cache_bytes:
            # clone: a view would keep the whole batch's feature tensors alive
            self._gt_cache[key] = [f.clone() for f in feats]
            self._gt_cache_used += size


def _image_key(img: np.ndarray) -> bytes:
    """Content key of one (H, W, 3) float32 image: its shape and the sha256 of its bytes."""
    return hashlib.sha256(np.ascontiguousarray(img).tobytes()).digest() + repr(img.shape).encode()


# --- all three ---------------------------------------------------------------------------
class Scorer:
    """PSNR, SSIM and LPIPS of image pairs with fixed protocols; reuse it across calls (LPIPS loads once).

    Parameters
    ----------
    ssim_protocol : {"3dgs", "skimage", "dmpix"}
    lpips_net : {"vgg", "alex"}, None or LPIPS
        None skips LPIPS; an :class:`LPIPS` instance is used as is.  When the weights are
        not set up, LPIPS values are None and :attr:`lpips_missing` says why and how to fix
        it (a warning is issued too): LPIPS is never silently zero.
    quantize : bool
        8-bit round trip of both images before every metric.
    device : str, optional
        LPIPS device.
    """

    def __init__(self, ssim_protocol: str = "3dgs", lpips_net: "str | LPIPS | None" = "vgg",
                 quantize: bool = True, device: str | None = None) -> None:
        self.ssim_protocol = get_ssim_protocol(ssim_protocol).name
        self.quantize = quantize
        self.lpips: LPIPS | None = None
        self.lpips_missing: str | None = None
        self.lpips_net = lpips_net.net if isinstance(lpips_net, LPIPS) else lpips_net
        if isinstance(lpips_net, LPIPS):
            self.lpips = lpips_net
        elif lpips_net is not None:
            try:
                self.lpips = LPIPS(lpips_net, device=device)
            except WeightsMissing as e:
                self.lpips_missing = f"LPIPS not computed: {e}"
                warnings.warn(self.lpips_missing, stacklevel=2)

    @property
    def protocol(self) -> dict:
        """Names of the protocols, for tables and results files."""
        return {
            "psnr": PSNR_PROTOCOL if self.quantize else "per image on [0, 1] (no quantisation); mean over views",
            "ssim": self.ssim_protocol,
            "ssim_reference": SSIM_PROTOCOLS[self.ssim_protocol].reference,
            "lpips": None if self.lpips_net is None else f"lpips-{self.lpips_net}-v0.1",
            "lpips_weights": None if self.lpips is None else self.lpips.weights,
            "quantize_8bit": self.quantize,
        }

    def __call__(self, preds: Sequence[np.ndarray], gts: Sequence[np.ndarray],
                 masks: Sequence[np.ndarray | None] | None = None) -> dict[str, list]:
        """Per-pair values of a sequence of pairs (images may differ in size between pairs).

        ``masks``: per pair, a bool (H, W) validity mask or None (every pixel counts); the
        metrics then follow :data:`MASK_PROTOCOL`.

        Returns
        -------
        dict
            ``{"psnr": [...], "ssim": [...], "lpips": [...] (None entries when not computed),
            "nonfinite": [...], "valid_fraction": [...]}`` (``nonfinite``: count of NaN / inf
            values in each prediction; ``valid_fraction``: share of valid pixels, None without a mask).
        """
        if len(preds) != len(gts):
            raise NimbusError(f"{len(preds)} predictions but {len(gts)} ground-truth images")
        if masks is not None and len(masks) != len(preds):
            raise NimbusError(f"{len(masks)} masks for {len(preds)} image pairs")
        out: dict[str, list] = {"psnr": [], "ssim": [], "lpips": [], "nonfinite": [], "valid_fraction": []}
        for group in _same_shape_runs([np.shape(p) for p in preds], [np.shape(g) for g in gts]):
            p = np.stack([np.asarray(preds[i], np.float32) for i in group])
            g = np.stack([np.asarray(gts[i], np.float32) for i in group])
            out["nonfinite"] += [int(n) for n in (~np.isfinite(p)).reshape(len(p), -1).sum(axis=1)]
            if self.quantize:  # once here, not in each metric
                p, g = quantize_8bit(p), quantize_8bit(g)
            given = [None if masks is None else masks[i] for i in group]
            m = None
            if any(x is not None for x in given):  # views without a mask count every pixel
                m = _mask_batch(np.stack([np.ones(p.shape[1:3], bool) if x is None else np.asarray(x)
                                          for x in given]), p.shape)
            out["valid_fraction"] += [None if x is None else float(mi.mean()) for x, mi in
                                      zip(given, m if m is not None else [None] * len(group))]
            out["psnr"] += psnr(p, g, quantize=False, mask=m).tolist()
            out["ssim"] += ssim(p, g, self.ssim_protocol, quantize=False, mask=m).tolist()
            if m is not None:  # the same background in both: the ground truth's
                p = np.where(m[..., None], p, g)
            out["lpips"] += (self.lpips(p, g, quantize=False).tolist() if self.lpips is not None
                             else [None] * len(group))
        return out


def _same_shape_runs(pred_shapes: list, gt_shapes: list, limit: int = 16) -> list[list[int]]:
    """Indices grouped into runs of consecutive pairs of one shape (at most ``limit`` each), checking pairs match."""
    for i, (ps, gs) in enumerate(zip(pred_shapes, gt_shapes)):
        if ps != gs:
            raise NimbusError(f"pair {i}: prediction {ps} and ground truth {gs} differ in shape; "
                              "render at the ground truth's resolution")
    runs: list[list[int]] = []
    for i, s in enumerate(pred_shapes):
        if runs and len(runs[-1]) < limit and pred_shapes[runs[-1][0]] == s:
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs


def _mean(values: list) -> float | None:
    if not values or any(v is None for v in values):
        return None
    return float(np.mean(values))


def score_images(preds: Sequence[np.ndarray], gts: Sequence[np.ndarray], ssim_protocol: str = "3dgs",
                 lpips_net: "str | LPIPS | None" = "vgg", names: Sequence[str] | None = None,
                 quantize: bool = True) -> dict:
    """PSNR, SSIM and LPIPS of every prediction against its ground truth, and their means.

    Parameters
    ----------
    preds, gts : sequence of arrays (H, W, 3), or arrays (B, H, W, 3); float in [0, 1]
        Pairs in the same order; sizes may differ between pairs, not within one.
    ssim_protocol : {"3dgs", "skimage", "dmpix"}
    lpips_net : {"vgg", "alex"}, None or LPIPS
        None skips LPIPS.  Without the weights set up, LPIPS is None with a note (never 0).
    names : sequence of str, optional
        View names (default ``"0", "1", ...``).
    quantize : bool
        8-bit round trip of both images first (the benchmark's convention).

    Returns
    -------
    dict
        ``per_view``: list of ``{"name", "psnr" (dB), "ssim" (<= 1), "lpips" (>= 0 or None)}``;
        ``mean``: the same three averaged over views (None where a value is missing);
        ``protocol``: the protocol names; ``notes``: list of str (missing LPIPS,
        non-finite predictions, infinite PSNR).
    """
    scorer = Scorer(ssim_protocol, lpips_net, quantize)
    names = [str(i) for i in range(len(preds))] if names is None else list(names)
    if len(names) != len(preds):
        raise NimbusError(f"{len(names)} names for {len(preds)} images")
    values = scorer(preds, gts)
    return summarize(names, values, scorer)


def summarize(names: Sequence[str], values: dict[str, list], scorer: Scorer) -> dict:
    """Per-view records, means, protocols and notes from :class:`Scorer` output (see :func:`score_images`)."""
    per_view = [{"name": n, "psnr": values["psnr"][i], "ssim": values["ssim"][i], "lpips": values["lpips"][i]}
                for i, n in enumerate(names)]
    fractions = values.get("valid_fraction") or [None] * len(names)
    masked = [f for f in fractions if f is not None]
    for rec, f in zip(per_view, fractions):
        if f is not None:
            rec.update(masked=True, valid_fraction=f)
    notes = []
    if scorer.lpips_missing:
        notes.append(scorer.lpips_missing)
    bad = [(n, c) for n, c in zip(names, values["nonfinite"]) if c]
    if bad:
        notes.append(f"{len(bad)} prediction(s) hold NaN / inf values (scored as an 8-bit PNG would store them: "
                     f"NaN -> 0, clipped): " + ", ".join(f"{n} ({c} values)" for n, c in bad[:5]))
    inf = [n for n, v in zip(names, values["psnr"]) if math.isinf(v)]
    if inf:
        notes.append(f"PSNR is infinite (prediction equals ground truth) for {len(inf)} view(s): {', '.join(inf[:5])}")
    protocol = scorer.protocol
    if masked:
        protocol["masks"] = MASK_PROTOCOL
        notes.append(f"{len(masked)} of {len(names)} view(s) have a validity mask and were scored over their valid "
                     f"pixels only (mean valid fraction {np.mean(masked):.3f})")
    return {
        "per_view": per_view,
        "mean": {k: _mean(values[k]) for k in ("psnr", "ssim", "lpips")},
        "masked": bool(masked),
        "masks": ({"views": len(masked), "mean_valid_fraction": float(np.mean(masked))} if masked else None),
        "protocol": protocol,
        "notes": notes,
        "lpips_missing": scorer.lpips_missing,
        "setup_command": SETUP_COMMAND if scorer.lpips_missing else None,
    }
