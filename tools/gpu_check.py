"""Does Nimbus work on this machine's GPU?  One command, one verdict line per check.

Usage::

    python -m tools.gpu_check [--iterations 150] [--scene builtin:garden:tiny]

On a CUDA machine, installing nothing, it checks:

1. ``torch vs reference``: the "torch" rasterizer backend on CUDA against the dense reference
   (:mod:`nimbus.render.reference`, on the CPU in float64): forward in float32 (max abs
   difference <= 1e-4) and gradients in float64 (``assert_close`` with atol 1e-9, rtol 1e-6).
2. ``gsplat vs torch`` / ``gsplat vs reference``: gsplat's CUDA rasterizer (when ``import gsplat``
   works; SKIP otherwise) against both, float32 forward.  gsplat clamps alpha at 0.999 (ours
   0.99) and bins with opacity-aware radii, so the images are close, not equal: mean abs
   difference <= 2e-3 and max <= 5e-2 (depth in units of the scene's farthest depth), the same
   Gaussians visible for >= 90 %, and a finite backward with the screen-space gradient filled.
3. ``march``: NimbusGS's ray march (torch, the path CUDA takes) on CUDA against the
   term-by-term :func:`~nimbus.methods.nimbusgs.scattering.march_reference` on the CPU in float64,
   transmission, scatter and the grid's gradient (atol 1e-5, rtol 1e-4).
4. ``train 3dgs`` / ``train nimbus-full``: the ``tiny`` preset (``--iterations`` steps, the
   schedule rescaled) on ``--scene`` on CUDA and on the CPU; PASS when the test PSNRs differ by
   at most :data:`PSNR_TOLERANCE_DB`.  The line also gives both runs' training seconds and the
   CUDA run's peak memory (the allocator's peak).  The two runs cannot be equal: the CPU uses the compiled
   kernels, CUDA gsplat (or torch) with other rounding, alpha clamp and non-deterministic
   atomics, and a few hundred steps of Adam and densification amplify any difference; a broken
   CUDA path costs many dB (or diverges), not a fraction of one.

Each line is ``PASS``, ``FAIL`` or ``SKIP`` with the check's name and its figures or reason; the exit
status is 1 when any check FAILs.  Without CUDA it says so and exits 0.  It takes about a minute
on an idle GPU machine with the compiled CPU kernels (most of it the CPU runs); beside twelve training
processes and with the kernels off (``NIMBUS_DISABLE_CPP=1``) its CPU 3DGS run alone took 210 s.  gsplat is installed separately, matching the
installed torch and CUDA (see the README).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass

import torch

from nimbus.errors import NimbusError

#: Largest |PSNR(cuda) - PSNR(cpu)| of the same training run, dB (see the module docstring).
PSNR_TOLERANCE_DB = 1.0
#: The random rasterizer scene: image size and Gaussian count (:func:`tools.speed.rasterizer.make_scene`).
RASTER_SCENE = (64, 48, 2_000)


@dataclass(frozen=True)
class Verdict:
    """One check's outcome: ``status`` PASS / FAIL / SKIP, and what it measured or why."""

    name: str
    status: str
    detail: str

    def line(self) -> str:
        return f"{self.status:<4}  {self.name}: {self.detail}"


def _outputs(out) -> list[torch.Tensor]:
    """rgb, depth, alpha of a rasterizer's output, on the CPU in float64."""
    return [x.detach().double().cpu() for x in out[:3]]


def _scene(dtype=torch.float32):
    from tools.speed.rasterizer import make_scene

    gs, cam = make_scene(*RASTER_SCENE)
    return gs.to(dtype=dtype), cam


def check_torch_vs_reference(device) -> Verdict:
    """The torch backend on ``device`` against the dense reference (float32 forward, float64 gradients)."""
    from nimbus.render import rasterize
    from nimbus.render.reference import rasterize_reference

    name = f"torch vs reference ({device})"
    gs, cam = _scene()
    ref = _outputs(rasterize_reference(gs, cam))
    ours = _outputs(rasterize(gs.to(device), cam, backend="torch"))
    fwd = max(float((a - b).abs().max()) for a, b in zip(ours, ref))
    if fwd > 1e-4:
        return Verdict(name, "FAIL", f"forward max |diff| {fwd:.2e} > 1e-4")
    gs64 = gs.to(dtype=torch.float64)
    grads = []
    for fn, where in ((rasterize_reference, "cpu"), (lambda g, c: rasterize(g, c, backend="torch"), device)):
        g = gs64.detach().to(where).requires_grad_()
        out = fn(g, cam)
        gen = torch.Generator().manual_seed(1)
        loss = sum((x * torch.randn(x.shape, generator=gen, dtype=x.dtype).to(x.device)).sum() for x in out[:3])
        loss.backward()
        grads.append({k: t.grad.cpu() for k, t in g.tensors().items()})
    for key, ref_grad in grads[0].items():
        try:
            torch.testing.assert_close(grads[1][key], ref_grad, atol=1e-9, rtol=1e-6)
        except AssertionError as exc:
            return Verdict(name, "FAIL", f"float64 gradient of {key}: {str(exc).splitlines()[0]}")
    return Verdict(name, "PASS", f"forward max |diff| {fwd:.1e} (float32), float64 gradients equal within rtol 1e-6")


def gsplat_missing(device) -> str | None:
    """Why gsplat cannot run on ``device`` here (None: it can)."""
    from nimbus.render import backends

    if torch.device(device).type != "cuda":
        return "gsplat is CUDA-only"
    try:
        import gsplat  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means "not usable here"
        return f"gsplat does not import ({type(exc).__name__}: {exc}); pip install gsplat to check it"
    return None if backends.available("gsplat", device) else "the gsplat backend is unavailable"


def check_gsplat(device) -> list[Verdict]:
    """gsplat on ``device`` against the torch backend and the reference (close, not equal)."""
    from nimbus.render import rasterize
    from nimbus.render.rasterize import means2d_grad
    from nimbus.render.reference import rasterize_reference

    why = gsplat_missing(device)
    if why:
        return [Verdict(f"gsplat vs {other}", "SKIP", why) for other in ("torch", "reference")]
    gs, cam = _scene()
    g = gs.to(device).requires_grad_()
    theirs_out = rasterize(g, cam, backend="gsplat")
    theirs = _outputs(theirs_out)
    far = float(gs.means[:, 2].max())
    verdicts = []
    for other, out in (("torch", rasterize(gs.to(device), cam, backend="torch")), ("reference",
                                                                                  rasterize_reference(gs, cam))):
        diffs = [(a - b).abs() / s for a, b, s in zip(theirs, _outputs(out), (1.0, far, 1.0))]
        mean, worst = max(float(d.mean()) for d in diffs), max(float(d.max()) for d in diffs)
        same = float((theirs_out[3]["visible"].cpu() == out[3]["visible"].cpu()).float().mean())
        ok = mean <= 2e-3 and worst <= 5e-2 and same >= 0.9
        verdicts.append(Verdict(f"gsplat vs {other} ({device})", "PASS" if ok else "FAIL",
                                f"mean |diff| {mean:.1e} (<= 2e-3), max {worst:.1e} (<= 5e-2), "
                                f"same visible {100 * same:.1f}% (>= 90%)"))
    theirs_out[0].sum().backward()
    grad = means2d_grad(theirs_out[3])
    finite = all(t.grad is not None and bool(torch.isfinite(t.grad).all()) for t in g.tensors().values())
    if grad is None or grad.shape != (len(gs), 2) or not finite:
        verdicts.append(Verdict(f"gsplat backward ({device})", "FAIL",
                                "missing or non-finite gradients, or no [N, 2] screen-space gradient"))
    return verdicts


def check_march(device) -> Verdict:
    """The torch ray march on ``device`` against the term-by-term reference (float64, CPU)."""
    from nimbus.methods.nimbusgs.scattering import Box, ExtinctionGrid, march, march_reference

    name = f"march vs reference ({device})"
    gen = torch.Generator().manual_seed(0)
    grid = ExtinctionGrid(Box((-1.0, -0.5, 0.0), (1.5, 1.0, 2.0)), 8, 1.5, 0.8, gen).double()
    with torch.no_grad():
        grid.features.normal_(0.0, 1.5, generator=gen)
    n = 500
    origin = torch.tensor([0.2, 0.1, -1.5], dtype=torch.float64)
    dirs = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.6
    dirs[:, 2] = 1.0
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t_start = torch.rand(n, generator=gen, dtype=torch.float64) * 2.0
    t_end = t_start + torch.rand(n, generator=gen, dtype=torch.float64) * 3.0
    weights = torch.randn(2, n, generator=gen, dtype=torch.float64)
    results = []
    for fn, where in ((march_reference, "cpu"), (lambda *a: march(*a, backend="torch"), device)):
        field = grid.to(where)
        field.zero_grad(set_to_none=True)
        res = fn(field, origin.to(where), dirs.to(where), t_start.to(where), t_end.to(where), 16)
        (res.transmission * weights[0].to(where) + res.scatter * weights[1].to(where)).sum().backward()
        # Copies: on the CPU .cpu() returns the gradient itself, and moving the grid to the GPU next swaps the
        # data of its parameters' gradients in place (Module.to), so the reference's gradient would move too.
        results.append([t.detach().cpu().clone() for t in (res.transmission, res.scatter, field.features.grad)])
    grid.to("cpu")
    try:
        for what, a, b in zip(("transmission", "scatter", "grid gradient"), results[1], results[0]):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4, msg=lambda m, w=what: f"{w}: {m}")
    except AssertionError as exc:
        return Verdict(name, "FAIL", str(exc).splitlines()[0])
    return Verdict(name, "PASS", "transmission, scatter and the grid's gradient equal within atol 1e-5")


def train_psnr(method: str, scene, device, iterations: int) -> tuple[float, float, float]:
    """Test PSNR (dB), training seconds and peak memory (MB: the CUDA allocator's peak on a GPU, the process's
    resident-set peak on the CPU) of ``method``'s ``tiny`` preset on ``scene``, trained on ``device``."""
    from nimbus.methods.registry import get_method
    from nimbus.train.runner import Runner

    config = get_method(method).preset("tiny").with_changes({"iterations": iterations})
    with tempfile.TemporaryDirectory(prefix="gpu_check_") as out:
        results = Runner(method, scene, config, out, seed=0, progress=False, checkpoints=False,
                         device=torch.device(device)).run()
    return float(results["psnr"]), float(results["train_time_s"]), float(results["peak_memory_mb"])


def check_training(method: str, scene, device, iterations: int, cpu_psnr: float | None = None) -> Verdict:
    """``method`` trained on ``device`` against the same run on the CPU (``cpu_psnr``: already measured)."""
    name = f"train {method} ({device} vs cpu, {iterations} steps)"
    psnr, seconds, peak_mb = train_psnr(method, scene, device, iterations)
    cpu_seconds = None
    if cpu_psnr is None:
        cpu_psnr, cpu_seconds, _ = train_psnr(method, scene, "cpu", iterations)
    diff = psnr - cpu_psnr
    ok = abs(diff) <= PSNR_TOLERANCE_DB
    cpu_time = "" if cpu_seconds is None else f" ({cpu_seconds:.1f} s on the CPU)"
    return Verdict(name, "PASS" if ok else "FAIL",
                   f"PSNR {psnr:.2f} dB vs {cpu_psnr:.2f} dB on the CPU ({diff:+.2f} dB, tolerance "
                   f"{PSNR_TOLERANCE_DB} dB), trained in {seconds:.1f} s{cpu_time}, peak memory {peak_mb:.0f} MB")


#: Print a crashed check's traceback to stderr (``--traceback``).
_TRACEBACKS = False


def _guarded(fn, name: str, *args) -> list[Verdict]:
    """``fn(*args)`` as verdicts; an exception is a FAIL naming it (and its traceback with ``--traceback``)."""
    try:
        out = fn(*args)
    except Exception as exc:  # noqa: BLE001 - a crash is this check's verdict, the others still run
        if _TRACEBACKS:
            traceback.print_exc(file=sys.stderr)
        return [Verdict(name, "FAIL", f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")]
    return out if isinstance(out, list) else [out]


def run_checks(device, scene_spec: str, iterations: int, methods=("3dgs", "nimbus-full")) -> list[Verdict]:
    """Every check on ``device``, each verdict printed as it comes; a bad ``scene_spec`` raises NimbusError
    before any check runs."""
    from nimbus.train.run_folder import load_scene_arg

    scene = load_scene_arg(scene_spec)
    verdicts = []

    def report(vs):
        for v in vs:
            print(v.line(), flush=True)
        verdicts.extend(vs)

    report(_guarded(check_torch_vs_reference, "torch vs reference", device))
    report(_guarded(check_gsplat, "gsplat", device))
    report(_guarded(check_march, "march vs reference", device))
    for method in methods:
        report(_guarded(check_training, f"train {method}", method, scene, device, iterations))
    return verdicts


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number >= 1")
    return value


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="builtin:garden:tiny", help="the scene trained on (default: %(default)s)")
    parser.add_argument("--iterations", type=_positive_int, default=150,
                        help="training steps per run (default: %(default)s)")
    parser.add_argument("--traceback", action="store_true", help="print a crashed check's traceback to stderr")
    args = parser.parse_args(argv)
    global _TRACEBACKS
    _TRACEBACKS = args.traceback
    if not torch.cuda.is_available():
        print(f"no CUDA device here (torch {torch.__version__}, built for CUDA {torch.version.cuda}): "
              "nothing to check; run this on a machine with an NVIDIA GPU")
        return 0
    t0 = time.perf_counter()
    print(f"GPU check on {torch.cuda.get_device_name(0)}, torch {torch.__version__}, CUDA {torch.version.cuda}",
          flush=True)
    try:
        verdicts = run_checks("cuda", args.scene, args.iterations)
    except NimbusError as exc:
        print(f"gpu_check: {exc}", file=sys.stderr)
        return 2
    failed = [v for v in verdicts if v.status == "FAIL"]
    print(f"{len(verdicts) - len(failed)} of {len(verdicts)} checks passed or skipped, {len(failed)} failed "
          f"({time.perf_counter() - t0:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
