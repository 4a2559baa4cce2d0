"""Speed of the benchmark metrics (PSNR, the three SSIM protocols, LPIPS AlexNet / VGG16), before and after.

Usage::

    python -m tools.speed.metrics [--views 50] [--size 320x240] [--nets vgg,alex] [--threads N]

Scores ``--views`` synthetic pairs (a smooth colour texture and a noisy copy) and prints
the seconds and milliseconds per view of each metric.  The issue's target is 50 views of
320 x 240 with all three metrics in seconds, not minutes.

Each speed-up is timed against the path it replaced, in the same run, on the same images
(with the largest difference of the values, which must stay below 1e-5):

* SSIM: OpenCV's float64 separable filter against the former banded-matrix product
  (:func:`ssim_banded_matmul`, kept here as the baseline), and the trainers' float32
  ``nimbus.metrics.ssim_map`` for scale;
* LPIPS: the onnxruntime trunk against torch (``backend="torch"``, the former path),
  both without the ground-truth cache (``backend="auto"`` picks per network, see
  ``nimbus.metrics.LPIPS_CPU_BACKEND``); then a second "method" scored against the
  same ground truth, where the cache spares the trunk half its images;
* the headline: ``score_images`` (PSNR + SSIM ``3dgs`` + LPIPS) per network, against the
  sum of the former paths' times.

Every row also gives the CPU seconds of all threads.  With other jobs on the two cores the
wall times swing by 2x from run to run and two threads can be slower than one; then
compare ``--threads 1`` runs, whose CPU seconds are stable to a few percent.

LPIPS uses the cached weights when ``nimbus-bench setup-weights`` has run, else random
weights of the same architecture (same cost; the values are then meaningless and marked).
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch

from benchmark.metrics import score_images
from nimbus.metrics import (LPIPS, LPIPS_CPU_BACKEND, SSIM_PROTOCOLS, WeightsMissing, peak_signal_noise_ratio,
                            quantize_8bit, random_state_dict, ssim_map, structural_similarity)
from nimbus.metrics.image import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW
from nimbus.metrics.lpips import LPIPS_GT_CACHE_MB


def make_pairs(n: int, width: int, height: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` smooth colour textures and noisy copies, float32 (n, H, W, 3) in [0, 1]."""
    rng = np.random.default_rng(seed)
    small = torch.from_numpy(rng.random((n, 3, height // 8 + 2, width // 8 + 2), dtype=np.float32))
    gt = torch.nn.functional.interpolate(small, size=(height, width), mode="bicubic", align_corners=False)
    gt = gt.clamp(0, 1).permute(0, 2, 3, 1).numpy()
    pred = np.clip(gt + rng.normal(0, 0.03, gt.shape).astype(np.float32), 0, 1)
    return pred, gt


def timed(fn, *args, **kwargs) -> tuple[float, object]:
    """Wall seconds of ``fn(*args, **kwargs)`` and its result; the call's CPU seconds go to ``timed.cpu``."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    timed.cpu = time.process_time() - c0
    return time.perf_counter() - t0, out


def lpips_model(net: str, **kwargs) -> tuple[LPIPS, str]:
    try:
        return LPIPS(net, device="cpu", **kwargs), "cached weights"
    except WeightsMissing:
        return LPIPS(net, device="cpu", state_dict=random_state_dict(net), **kwargs), "RANDOM weights (not set up)"


@functools.lru_cache(maxsize=4)  # as the former path cached its matrices
def _band(n: int) -> torch.Tensor:
    """(n, n) float64 weights of inputs on outputs of the 1-D Gaussian filter, zero 'same' padding."""
    half = SSIM_WINDOW // 2
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - half
    taps = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    taps = taps / taps.sum()
    k = torch.arange(n)[:, None] - torch.arange(n)[None, :] + half
    return torch.where((k >= 0) & (k < SSIM_WINDOW), taps[k.clamp(0, SSIM_WINDOW - 1)], 0.0)


def ssim_banded_matmul(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """The former SSIM ``3dgs`` path (baseline): each 1-D Gaussian pass a float64 product with a banded matrix.

    ``pred``, ``gt``: quantised (n, H, W, 3) float32 -> (n,) float64 mean SSIM.
    """
    out = []
    with torch.inference_mode():
        for s in range(0, len(pred), 8):
            a, b = (torch.from_numpy(v[s:s + 8]).double().permute(0, 3, 1, 2).flatten(0, 1) for v in (pred, gt))
            bw, bh = _band(a.shape[2]), _band(a.shape[1])
            mu_x, mu_y, exx, eyy, exy = (bh.T @ torch.cat([a, b, a * a, b * b, a * b]) @ bw).chunk(5)
            sxx, syy, sxy = exx - mu_x**2, eyy - mu_y**2, exy - mu_x * mu_y
            m = ((2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
                 / ((mu_x**2 + mu_y**2 + SSIM_C1) * (sxx + syy + SSIM_C2)))
            out.append(m.reshape(-1, 3 * m.shape[1] * m.shape[2]).mean(dim=1))
    return torch.cat(out).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=50)
    ap.add_argument("--size", default="320x240", help="WIDTHxHEIGHT")
    ap.add_argument("--nets", default="vgg,alex", help="LPIPS networks to time (comma-separated)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--gt-cache-mb", type=float, default=4096,
                    help="LPIPS ground-truth cache of the 2nd-method figure (MiB; the library default is "
                         f"{LPIPS_GT_CACHE_MB:g}, ~27 views of 320x240 with VGG)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    w, h = (int(v) for v in args.size.lower().split("x"))
    n = args.views
    pred, gt = make_pairs(n, w, h)
    qp, qg = quantize_8bit(pred), quantize_8bit(gt)
    print(f"{n} views of {w}x{h}, torch threads {torch.get_num_threads()}")

    def row(label: str, seconds: float, extra: str = "") -> None:
        # CPU seconds (all threads) beside the wall time: less sensitive to other jobs on the cores
        print(f"  {label:<40} {seconds:7.2f} s  {1000 * seconds / n:8.1f} ms/view  (cpu {timed.cpu:6.1f} s)  {extra}")

    structural_similarity(pred[:1], gt[:1])  # first calls initialise thread pools and kernels; not part of the figures
    ssim_banded_matmul(qp[:1], qg[:1])
    psnr_sec, v = timed(peak_signal_noise_ratio, pred, gt)
    row("PSNR", psnr_sec, f"mean {np.mean(v):.3f} dB")
    for name in SSIM_PROTOCOLS:
        sec, v = timed(structural_similarity, pred, gt, protocol=name)
        row(f"SSIM {name} (float64)", sec, f"mean {np.mean(v):.5f}")
        if name == "3dgs":
            ssim_sec, ssim_v = sec, v
    before, v = timed(ssim_banded_matmul, qp, qg)
    row("before: SSIM 3dgs, banded matmul", before, f"mean {np.mean(v):.5f}  (before / now: {before / ssim_sec:.2f}x, "
        f"max |diff| {np.abs(v - ssim_v).max():.1e})")
    ssim_before = before
    with torch.inference_mode():
        base, v = timed(lambda: [ssim_map(torch.from_numpy(qp[s:s + 8]), torch.from_numpy(qg[s:s + 8]))
                                 .double().mean(dim=(1, 2, 3)) for s in range(0, n, 8)])
    v = torch.cat(v).numpy()
    row("scale: trainers' ssim_map float32", base, f"mean {np.mean(v):.5f}  (now / this: {ssim_sec / base:.2f}x)")

    for net in [s for s in args.nets.split(",") if s]:
        old, what = lpips_model(net, backend="torch", gt_cache_mb=0)
        ort, _ = lpips_model(net, backend="onnxruntime", gt_cache_mb=0)
        new = old if LPIPS_CPU_BACKEND[net] == "torch" else ort  # what backend="auto" picks on the CPU
        cached, _ = lpips_model(net, gt_cache_mb=args.gt_cache_mb)
        for lp in (old, ort, cached):
            lp(pred[:1], gt[:1])  # first call initialises the kernels; not part of the figure
        old_sec, v_old = timed(old, pred, gt)
        row(f"before: LPIPS {net}, torch trunk", old_sec, f"mean {np.mean(v_old):.4f}  ({what})")
        ort_sec, v_ort = timed(ort, pred, gt)
        row(f"LPIPS {net}, onnxruntime trunk", ort_sec,
            f"mean {np.mean(v_ort):.4f}  (torch / onnxruntime: {old_sec / ort_sec:.2f}x, "
            f"max |diff| {np.abs(v_ort - v_old).max():.1e})")
        new_sec = ort_sec if new is ort else old_sec
        print(f"  -> backend 'auto' runs the {net} trunk with {new.backend}")
        timed(cached, pred, gt)  # the first method fills the cache
        other = np.clip(pred * 0.9 + 0.05, 0, 1)
        again, _ = timed(cached, other, gt)
        row(f"LPIPS {net}, 2nd method, same GT (cache)", again,
            f"({cached.backend}; {cached.cached_views} views cached in {args.gt_cache_mb:g} MiB; "
            f"before / now: {old_sec / again:.2f}x)")
        sec, res = timed(score_images, list(pred), list(gt), "3dgs", new)
        print(f"  all three (PSNR + SSIM 3dgs + LPIPS {net}, {new.backend}), {n} views of {w}x{h}: now {sec:.1f} s "
              f"(cpu {timed.cpu:.1f} s); before (sum of the former paths) {psnr_sec + ssim_before + old_sec:.1f} s; "
              f"LPIPS alone now {new_sec:.1f} s; means: PSNR {res['mean']['psnr']:.3f}, "
              f"SSIM {res['mean']['ssim']:.4f}, LPIPS {res['mean']['lpips']:.4f}")

if __name__ == "__main__":
    main()
