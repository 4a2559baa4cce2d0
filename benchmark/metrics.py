"""The benchmark's scoring of image sets: per-view PSNR, SSIM and LPIPS, means, protocol names and notes.

The metrics themselves are :mod:`nimbus.metrics` (shared with training); their conventions
(8-bit round trip, SSIM protocols, validity masks) are in :mod:`nimbus.metrics.image`.  This
module adds what a benchmark record needs: pairs of several sizes scored in batches, views
with and without masks, LPIPS that reports missing weights rather than zero, and notes on
non-finite predictions and infinite PSNR.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from nimbus.errors import NimbusError
from nimbus.metrics import (LPIPS, MASK_PROTOCOL, PSNR_PROTOCOL, SETUP_COMMAND, SSIM_PROTOCOLS, WeightsMissing,
                            get_ssim_protocol, mask_batch, peak_signal_noise_ratio, quantize_8bit,
                            structural_similarity)

@dataclass(frozen=True)
class EvalProtocol:
    """A named way of scoring a benchmark's renders (``nimbus-bench run --protocol``).

    Attributes
    ----------
    name : str
    quantize : bool
        8-bit round trip of renders and ground truth before every metric (renders scored as the PNGs
        they are saved as); False scores float renders.
    ssim : str or None
        The SSIM protocol it fixes (None: ``--ssim`` chooses).
    lpips : str or None
        The LPIPS network it fixes (None: ``--lpips`` chooses).
    summary : str
    """

    name: str
    quantize: bool
    ssim: str | None
    lpips: str | None
    summary: str


#: The benchmark's evaluation protocols.  ``default`` is the benchmark's own (every committed table); ``paper`` is
#: the evaluation of the 3DGS and NimbusGS papers' scripts: PSNR of the float render (no 8-bit rounding), the
#: 3DGS SSIM (11x11 Gaussian window, sigma 1.5, zero padding) and LPIPS-VGG.
EVAL_PROTOCOLS = {
    "default": EvalProtocol("default", True, None, None,
                            "renders and ground truth through an 8-bit round trip; --ssim and --lpips choose"),
    "paper": EvalProtocol("paper", False, "3dgs", "vgg",
                          "the papers' evaluation: PSNR on float renders (no 8-bit rounding), 3DGS SSIM, LPIPS-VGG"),
}


def get_eval_protocol(name: str) -> EvalProtocol:
    if name not in EVAL_PROTOCOLS:
        raise NimbusError(f"unknown evaluation protocol {name!r}; use one of {', '.join(EVAL_PROTOCOLS)}")
    return EVAL_PROTOCOLS[name]


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
                m = mask_batch(np.stack([np.ones(p.shape[1:3], bool) if x is None else np.asarray(x)
                                          for x in given]), p.shape)
            out["valid_fraction"] += [None if x is None else float(mi.mean()) for x, mi in
                                      zip(given, m if m is not None else [None] * len(group))]
            out["psnr"] += peak_signal_noise_ratio(p, g, quantize=False, mask=m).tolist()
            out["ssim"] += structural_similarity(p, g, protocol=self.ssim_protocol, quantize=False,
                                                 mask=m).tolist()
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
