"""Speed of the benchmark metrics (PSNR, the three SSIM protocols, LPIPS AlexNet / VGG16).

Usage::

    python -m benchmark.bench_metrics [--views 50] [--size 320x240] [--nets vgg,alex] [--threads N]

Scores ``--views`` synthetic pairs (a smooth colour texture and a noisy copy) and prints
the seconds and milliseconds per view of each metric, then the headline figure: what
``score_images`` with the defaults (PSNR, SSIM ``3dgs``, LPIPS VGG) costs for all views.
The issue's target is 50 views of 320 x 240 with all three metrics in seconds, not minutes.

Baseline (same run): the trainers' float32 SSIM (``nimbus.losses.ssim_map``, a depthwise
convolution) on the same images; the ratio says what the benchmark's float64 SSIM (exact
to ~1e-15, see :mod:`benchmark.metrics`) costs against it.

LPIPS uses the cached weights when ``nimbus-bench setup-weights`` has run, else random
weights of the same architecture (same cost; the values are then meaningless and marked).
Figures depend on the machine's load: with other jobs on the two cores, two torch threads
can be slower than one (``--threads 1``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from benchmark.lpips import random_state_dict
from benchmark.metrics import LPIPS, SSIM_PROTOCOLS, psnr, quantize_8bit, score_images, ssim
from benchmark.weights import WeightsMissing
from nimbus.losses import ssim_map


def make_pairs(n: int, width: int, height: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` smooth colour textures and noisy copies, float32 (n, H, W, 3) in [0, 1]."""
    rng = np.random.default_rng(seed)
    small = torch.from_numpy(rng.random((n, 3, height // 8 + 2, width // 8 + 2), dtype=np.float32))
    gt = torch.nn.functional.interpolate(small, size=(height, width), mode="bicubic", align_corners=False)
    gt = gt.clamp(0, 1).permute(0, 2, 3, 1).numpy()
    pred = np.clip(gt + rng.normal(0, 0.03, gt.shape).astype(np.float32), 0, 1)
    return pred, gt


def timed(fn, *args, **kwargs) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return time.perf_counter() - t0, out


def lpips_model(net: str) -> tuple[LPIPS, str]:
    try:
        return LPIPS(net, device="cpu"), "cached weights"
    except WeightsMissing:
        return LPIPS(net, device="cpu", state_dict=random_state_dict(net)), "RANDOM weights (not set up)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=50)
    ap.add_argument("--size", default="320x240", help="WIDTHxHEIGHT")
    ap.add_argument("--nets", default="vgg,alex", help="LPIPS networks to time (comma-separated)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    w, h = (int(v) for v in args.size.lower().split("x"))
    n = args.views
    pred, gt = make_pairs(n, w, h)
    print(f"{n} views of {w}x{h}, torch threads {torch.get_num_threads()}")

    def row(label: str, seconds: float, extra: str = "") -> None:
        print(f"  {label:<28} {seconds:7.2f} s  {1000 * seconds / n:8.1f} ms/view  {extra}")

    sec, v = timed(psnr, pred, gt)
    row("PSNR", sec, f"mean {np.mean(v):.3f} dB")
    for name in SSIM_PROTOCOLS:
        sec, v = timed(ssim, pred, gt, name)
        row(f"SSIM {name} (float64)", sec, f"mean {np.mean(v):.5f}")
        if name == "3dgs":
            ssim_sec = sec
    qp, qg = torch.from_numpy(quantize_8bit(pred)), torch.from_numpy(quantize_8bit(gt))
    with torch.inference_mode():
        base, v = timed(lambda: [ssim_map(qp[s:s + 8], qg[s:s + 8]).double().mean(dim=(1, 2, 3))
                                 for s in range(0, n, 8)])
    v = torch.cat(v).numpy()
    row("baseline: ssim_map float32", base, f"mean {np.mean(v):.5f}  (benchmark / baseline: {ssim_sec / base:.2f}x)")

    models = {}
    for net in [s for s in args.nets.split(",") if s]:
        lp, what = lpips_model(net)
        lp(pred[:1], gt[:1])  # first call initialises oneDNN kernels; not part of the figure
        sec, v = timed(lp, pred, gt)
        row(f"LPIPS {net}", sec, f"mean {np.mean(v):.4f}  ({what})")
        models[net] = lp

    lp = models.get("vgg") or lpips_model("vgg")[0]
    sec, res = timed(score_images, list(pred), list(gt), "3dgs", lp)
    print(f"score_images (PSNR + SSIM 3dgs + LPIPS vgg), {n} views of {w}x{h}: {sec:.1f} s "
          f"({1000 * sec / n:.0f} ms/view); means: PSNR {res['mean']['psnr']:.3f}, SSIM {res['mean']['ssim']:.4f}, "
          f"LPIPS {res['mean']['lpips']:.4f}")


if __name__ == "__main__":
    main()
