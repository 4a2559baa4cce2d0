"""LPIPS as a metric: the callable :class:`LPIPS` (weights from the cache, batching, devices, back ends).

LPIPS v0.1 (Zhang et al., CVPR 2018): the network is :mod:`nimbus.metrics.lpips_network`, its
trunk optionally run by onnxruntime (:mod:`nimbus.metrics.lpips_onnx`), its weights set up once
by ``nimbus-bench setup-weights`` (:mod:`nimbus.metrics.lpips_weights`).

Inputs follow :mod:`nimbus.metrics.image`: numpy RGB float images in [0, 1], ``(H, W, 3)`` or
``(B, H, W, 3)``, put through the 8-bit round trip first unless ``quantize=False``.  With a
validity mask, LPIPS is of whole images after the prediction's invalid pixels are replaced by
the ground truth's (the peers' practice: both images on the same background; the distance is
then diluted by the invalid fraction); the caller does that replacement (the benchmark's scorer).
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np
import torch

from nimbus.errors import NimbusError
from nimbus.metrics.image import as_batches
from nimbus.metrics.lpips_network import LPIPS_NETS, LPIPSNetwork, min_input_size, unit_normalize
from nimbus.metrics.lpips_onnx import OnnxTrunk
from nimbus.metrics.lpips_weights import load_weights, weights_info

LPIPS_BATCH = 4      # image pairs per LPIPS batch: VGG on 320x240 needs ~0.1 GB per pair
LPIPS_GT_CACHE_MB = 1024  # memory for cached ground-truth LPIPS features (MiB; see LPIPS)
LPIPS_BACKENDS = ("auto", "onnxruntime", "torch")
#: What ``backend="auto"`` runs each trunk with on the CPU: onnxruntime where it took less CPU time
#: (VGG: ~1.2x less), torch where it did not (AlexNet: ~10% more with onnxruntime); see
#: tools/speed/metrics.py.  Other devices use torch.
LPIPS_CPU_BACKEND = {"vgg": "onnxruntime", "alex": "torch"}


class LPIPS:
    """Learned perceptual image patch similarity (LPIPS v0.1), callable on images or batches.

    Parameters
    ----------
    net : {"vgg", "alex"}
        Trunk; ``"vgg"`` is the paper's (and 3DGS's) evaluation, ``"alex"`` nerfbaselines' default.
    device : str or torch.device, optional
        Default: CUDA when available, else CPU.
    state_dict : dict, optional
        Weights in :class:`nimbus.metrics.lpips_network.LPIPSNetwork`'s layout; default: the cache written by
        ``nimbus-bench setup-weights``.  Tests pass random weights.
    batch_size : int
        Image pairs per forward pass (bounds memory; default ``LPIPS_BATCH``).
    backend : {"auto", "onnxruntime", "torch"}
        What runs the trunk.  ``auto`` (default): on the CPU, :data:`LPIPS_CPU_BACKEND`
        (onnxruntime for VGG, :mod:`nimbus.metrics.lpips_onnx`; torch for AlexNet); torch on
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
        a, b, single = as_batches(pred, gt, quantize)
        need = min_input_size(self.net)
        if min(a.shape[1], a.shape[2]) < need:
            raise NimbusError(f"LPIPS-{self.net} needs images of at least {need}x{need} pixels, got "
                              f"{a.shape[2]}x{a.shape[1]}")
        out = np.empty(len(a), np.float64)
        with torch.inference_mode():
            for s in range(0, len(a), self.batch_size):
                fa, fb = self._pair_features(a[s:s + self.batch_size], b[s:s + self.batch_size])
                out[s:s + len(fa[0])] = self.network.distance(fa, fb).double().cpu().numpy()
        return float(out[0]) if single else out

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
