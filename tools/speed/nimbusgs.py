"""Where a NimbusGS training iteration spends its time: per-component wall and CPU milliseconds.

Usage::

    python -m tools.speed.nimbusgs [--scene builtin:garden:small] [--preset fast] [--repeats 5]
                                   [--threads N] [--reference] [--checkpoint RUN/checkpoint.pt]

Builds a :class:`~nimbus.methods.nimbusgs.NimbusGS` (through :class:`~nimbus.train.runner.Runner`, so in
its training frame) on ``--scene`` (a scene folder,
e.g. a ``nimbus-synth degrade`` setting, or ``builtin:NAME:SIZE``) with the preset's
settings and every component forced on (``components=csm,plm,ggs``), then times, on
the first training view, each piece of an iteration: the rasterizer (forward +
backward), the ray march (forward + backward; ``torch`` and the compiled ``cpp``
backend, and with ``--reference`` the term-by-term :func:`march_reference`), the march
interval, the airlight network (at the preset's ``airlight_stride``, as training evaluates it, and at
every pixel), the photometric loss (L1 + SSIM), L_DCP, L_TV, GGS,
the optimiser step, one whole stage-1 and stage-2 ``train_iteration`` (densification off, so every
repeat times the same model), and the stage-boundary
and periodic PLM refresh (every training view rendered and composed, plus the
view-consistency check), and that check alone on one view (torch, and the compiled kernel),
and the gradient guard alone.  Each row is the median of ``--repeats`` runs after one
warm-up (the refresh and stage boundary: one run); ``cpu ms`` is the process CPU time
over the same run, which on a machine shared with other jobs tells the work apart from
the waiting.  The Gaussians are the scene's initial ones (their count is printed), or
with ``--checkpoint`` those of a NimbusGS run on the same scene and preset (its
Gaussians and medium; the rasterizer's share grows with densification, the medium's
does not).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time

import torch

from nimbus.methods.gs3d import GaussianSplatting
from nimbus.methods.nimbusgs.ggs import scale_gradients
from nimbus.methods.nimbusgs.particulate import _excess_torch, is_refresh_step
from nimbus.methods.nimbusgs.scattering import march, march_interval, march_reference
from tools.speed import load_average, openmp_wait


def _time(fn, repeats: int, warmup: int = 1) -> tuple[float, float]:
    """Median wall and CPU milliseconds of ``fn()`` over ``repeats`` runs."""
    for _ in range(warmup):
        fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return 1e3 * statistics.median(walls), 1e3 * statistics.median(cpus)


def build_method(scene_spec: str, preset_name: str, out: str, checkpoint: str | None = None):
    """NimbusGS with every component on and densification off; ``checkpoint``: a run's state (Gaussians and
    medium) loaded."""
    from pathlib import Path

    from nimbus.methods.nimbusgs.config import preset
    from nimbus.train.run_folder import load_scene_arg
    from nimbus.train.runner import Runner

    config = dataclasses.replace(preset(preset_name), components="csm,plm,ggs", write_decomposition=False)
    runner = Runner("nimbus", load_scene_arg(scene_spec), config, out, seed=0, progress=False)
    tr = runner.method
    if checkpoint:
        runner.load_checkpoint(Path(checkpoint))
        if not tr.use_csm:
            raise SystemExit("the checkpoint's run has no medium (CSM off): nothing to time")
        tr.use_plm = tr.use_ggs = True  # time every component whatever the run chose
        tr.particulate = None
    # Repeats of one step must time the same model: no densification, pruning or opacity reset.
    tr.strategy = dataclasses.replace(tr.strategy, densify_from=10**9, opacity_reset_interval=10**9)
    return tr


def train_step(tr, vi: int, it: int) -> None:
    """The method's whole ``train_iteration`` on view ``vi`` as step ``it``."""
    tr._order = [vi]  # the view the step takes next
    tr.train_iteration(it)


def component_rows(tr, repeats: int, reference: bool) -> list[tuple[str, float, float]]:
    c = tr.cfg
    vi, it1, it2 = 0, max(c.m_init // 2, 1), max(c.m_init + 1, c.iterations - 1)  # it2: full SH degree
    while it2 > c.m_init + 1 and is_refresh_step(it2, c.m_init, c.refresh_interval):
        it2 -= 1  # a step without the periodic refresh (timed on its own below)
    view, gt = tr.train_views[vi], tr.train_images[vi]
    rays = tr._rays_for(vi)
    medium = tr.medium
    lo, hi = medium.box_tensors
    rows = []

    def add(name, fn, n=repeats, warmup=1):
        rows.append((name, *_time(fn, n, warmup)))
        tr.params.optimizer.zero_grad(set_to_none=True)
        medium.optimizer.zero_grad(set_to_none=True)

    def render_fb():
        r = tr.render(view.camera, c.sh_degree)
        (r["rgb"].sum() + r["depth"].sum()).backward()

    add("render fwd+bwd (rasterizer)", render_fb)
    with torch.no_grad():
        r = tr.render(view.camera, c.sh_degree)
    depth, alpha = r["depth"], r["alpha"]
    ts, te = march_interval(rays, lo, hi, depth, alpha, c.near_plane, c.surface_alpha_min)
    weights = torch.randn(2, ts.shape[0], generator=torch.Generator().manual_seed(0))

    def march_fb(fn):
        def run():
            res = fn()
            (res.transmission * weights[0] + res.scatter * weights[1]).sum().backward()
        return run

    K = c.ray_samples
    if reference:
        add("march fwd+bwd (reference)", march_fb(lambda: march_reference(medium.field, rays.origin, rays.dirs, ts, te, K)))
    add("march fwd+bwd (torch)", march_fb(lambda: march(medium.field, rays.origin, rays.dirs, ts, te, K, "torch")))
    try:
        add("march fwd+bwd (cpp)", march_fb(lambda: march(medium.field, rays.origin, rays.dirs, ts, te, K, "cpp")))
    except Exception as exc:  # noqa: BLE001 - report and go on
        print(f"compiled march unavailable: {exc}")
    add("march interval", lambda: march_interval(rays, lo, hi, depth, alpha, c.near_plane, c.surface_alpha_min))
    transmission = torch.rand(ts.shape[0])
    # As training evaluates it: once per airlight_stride x airlight_stride block, then upsampled (fast: 2 x 2).
    add(f"airlight fwd+bwd (stride {c.airlight_stride})",
        lambda: medium._airlight(rays, transmission, tr.descriptors[vi], gt).sum().backward())
    if c.airlight_stride != 1 and c.airlight == "network":
        add("airlight fwd+bwd (every pixel)",
            lambda: medium.airlight(rays.dirs, transmission, tr.descriptors[vi], gt.reshape(-1, 3)).sum().backward())
    pred = gt.clone().mul_(0.9).requires_grad_()
    from nimbus.methods.nimbusgs.losses import dcp_loss, stage_loss

    add("L1 + SSIM fwd+bwd", lambda: stage_loss(pred, gt, c.lambda_dssim).backward())
    add("L_DCP fwd+bwd", lambda: dcp_loss(pred, c.dcp_patch, c.dcp_temperature, c.dcp_form).backward())
    add("L_TV fwd+bwd", lambda: medium.field.tv().backward())

    def step_at(it):
        return lambda: train_step(tr, vi, it)

    add(f"stage-1 iteration (all of it, it {it1})", step_at(it1))
    t0 = time.perf_counter()
    c0 = time.process_time()
    tr._end_stage1(c.m_init)
    rows.append(("stage boundary (evidence + first R)", 1e3 * (time.perf_counter() - t0),
                 1e3 * (time.process_time() - c0)))
    check = tr._consistency_check()
    if check is not None and check.others[vi]:
        geometry = tr._surfaces if tr._surfaces is not None else tr._composites(c.m_init)[1]
        own, others = check._view(vi), [(geometry[j], check._view(j)) for j in check.others[vi]]
        rows.append((f"consistency check, one view, {len(others)} neighbours (torch)",
                     *_time(lambda: _excess_torch(check.images[vi], geometry[vi], own, others), repeats)))
        rows.append(("consistency check, one view (compiled where it builds)",
                     *_time(lambda: check.excess(vi, geometry), repeats)))
    add(f"stage-2 iteration (all of it, it {it2})", step_at(it2))
    # GGS and the optimiser step alone, after a stage-2 forward/backward.
    r2 = tr.render(view.camera, c.sh_degree)
    loss, pred = tr.loss(it2, vi, r2, gt)
    loss.backward()
    rows.append(("gradient guard alone (every gradient)", *_time(lambda: GaussianSplatting._grads_finite(tr), repeats)))
    rows.append(("GGS weights (before_backward)", *_time(lambda: tr.before_backward(it2, vi, r2, pred, gt), repeats)))
    weights = tr._ggs_weights[0]
    tr._ggs_weights = None
    # Where the rasterizer's backward does not fold the weights in (other backends), GGS scales afterwards.
    rows.append(("GGS scaling after backward, with the guard of what it scales (no fold)",
                 *_time(lambda: scale_gradients(tr.params.tensors, weights), repeats)))

    def opt_step():
        for group in tr.param_groups():
            for p in group["params"]:
                if p.grad is None:
                    p.grad = torch.zeros_like(p)
        tr.optimizer_step()

    add("optimiser step (Gaussians + medium)", opt_step)
    t0 = time.perf_counter()
    c0 = time.process_time()
    tr._refresh_all(c.m_init + c.refresh_interval)
    rows.append((f"PLM refresh ({len(tr.train_views)} views)", 1e3 * (time.perf_counter() - t0),
                 1e3 * (time.process_time() - c0)))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="builtin:garden:small")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--reference", action="store_true", help="also time march_reference")
    parser.add_argument("--checkpoint", default=None, help="a NimbusGS run's checkpoint.pt on the same scene")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="bench_nimbusgs_") as out:
        tr = build_method(args.scene, args.preset, out, args.checkpoint)
        cam = tr.train_views[0].camera
        c = tr.cfg
        print(f"scene {args.scene}, preset {args.preset}: {len(tr.train_views)} training views {cam.width}x"
              f"{cam.height}, {len(tr.params)} Gaussians, grid {c.grid_resolution}^3, K = {c.ray_samples}, "
              f"{torch.get_num_threads()} threads; {openmp_wait()}; load average {load_average()}")
        rows = component_rows(tr, args.repeats, args.reference)
    width = max(len(r[0]) for r in rows)
    print(f"{'component':<{width}}  {'wall ms':>9}  {'cpu ms':>9}")
    for name, wall, cpu in rows:
        print(f"{name:<{width}}  {wall:9.1f}  {cpu:9.1f}")
    print(f"load average after: {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
