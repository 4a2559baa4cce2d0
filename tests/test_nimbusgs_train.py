"""NimbusGS through the runner: outputs, component choice, GGS on densification, extremes, resume, quality."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from nimbus.data.builtin import render_builtin
from nimbus.data.scene import View
from nimbus.errors import NimbusError
from nimbus.methods.nimbusgs.auto import particle_thresholds
from nimbus.methods.nimbusgs.config import NimbusConfig
from nimbus.methods.nimbusgs.ggs import ggs_weights, ndc_grad_norm
from nimbus.methods.nimbusgs.method import NimbusGS
from nimbus.render.rasterize import means2d_grad
from nimbus.train.checkpoint import CHECKPOINT
from nimbus.train.runner import Runner
from weather_synth.dataset import DegradedPointColours
from weather_synth.depth import DepthConfig

FULL = "csm,plm,ggs"


def _downscale(scene, f=2):
    views = []
    for v in scene.views:
        h, w = v.image.shape[:2]
        img = v.image.reshape(h // f, f, w // f, f, 3).mean((1, 3)).astype(np.float32)
        depth = v.depth.reshape(h // f, f, w // f, f).mean((1, 3)).astype(np.float32)
        views.append(View(v.name, v.camera.scaled(1.0 / f), image=img, depth=depth))
    return scene.with_views(views)


def _degrade(scene, beta=0.0, streaks=0, seed=0, airlight=(0.85, 0.86, 0.9), amplitude=0.6):
    """Training views with haze ``I = J t + A (1 - t)``, ``t = exp(-beta * ray distance)`` and/or bright streaks."""
    rng = np.random.default_rng(seed)
    views = []
    for v in scene.views:
        img = v.image.copy()
        if v.name not in scene.test_names:
            if beta > 0:
                t = np.exp(-beta * v.camera.ray_distance_from_z(v.depth))[..., None]
                img = img * t + np.asarray(airlight, np.float32) * (1 - t)
            h, w = img.shape[:2]
            for _ in range(streaks):
                x, y = rng.integers(0, w), rng.integers(0, h)
                ys = np.arange(y, min(h, y + int(rng.integers(3, max(4, h // 4)))))
                img[ys, np.clip(x + (ys - y) // 4, 0, w - 1)] += amplitude
            img = np.clip(img, 0, 1).astype(np.float32)
        views.append(View(v.name, v.camera, image=img, depth=v.depth))
    # As nimbus-synth degrade: the sparse points take their colours from the degraded training views, so no
    # method starts from the clean colours.
    colours = DegradedPointColours(scene.points, DepthConfig())
    for v in views:
        if v.name not in scene.test_names:
            colours.add(v.camera, np.rint(v.image * 255).astype(np.uint8))
    return dataclasses.replace(scene.with_views(views), colors=colours.colours())


@pytest.fixture(scope="module")
def clean():
    """The tiny garden at 32 x 24 px: 7 training views, 2 test views (clean)."""
    s = _downscale(render_builtin("garden", size="tiny", seed=0))
    return s.with_views(s.train_views[::2] + s.test_views)


@pytest.fixture(scope="module")
def hazy(clean):
    return _degrade(clean, beta=0.06)


@pytest.fixture(scope="module")
def rainy(clean):
    return _degrade(clean, streaks=24)


#: Particle thresholds the test scenes below are told apart at (a 32 x 24 garden after 40 stage-1 iterations: its
#: one-pixel flowers give the clean scene a tail asymmetry of 0.33, which the defaults, derived on the validation
#: scenes at the tiny size, call rainy).  The haze pair differs, so a record shows which pair judged a scene.
SEPARATING_THRESHOLDS = dict(auto_particle_threshold=0.35, auto_particle_energy=0.0005,
                             auto_particle_threshold_haze=0.3, auto_particle_energy_haze=0.0004)


def _cfg(**kw):
    base = dict(iterations=16, m_init=6, refresh_interval=4, components=FULL, sh_degree=1, sh_degree_interval=8,
                densify_from=4, densify_until=12, densify_interval=4, opacity_reset_interval=1000,
                checkpoint_interval=8, log_interval=4, grid_resolution=8, ray_samples=8, dcp_patch=5,
                airlight_hidden=8)
    base.update(kw)
    return NimbusConfig(**base)


def _nimbus(scene, cfg, out, seed=0) -> Runner:
    return Runner("nimbus", scene, cfg, out, seed=seed, progress=False)


def _finite_state(m: NimbusGS) -> bool:
    tensors = list(m.params.tensors.values())
    if m.medium is not None:  # extinction and airlight
        tensors += [p for group in m.medium.param_groups() for p in group["params"]]
    return all(torch.isfinite(x).all() for x in tensors)


def test_full_model_trains_and_writes_the_decomposition(hazy, tmp_path):
    t = _nimbus(hazy, _cfg(), tmp_path / "run")
    res = t.run()
    n, cam = len(hazy.train_views), hazy.train_views[0].camera
    nim = res["nimbus"]
    assert res["components"] == ["csm", "plm", "ggs"] and nim["mode"] == "forced"
    # R of every view after stage 1, then (refresh_mode=lazy) a view's own at its first draw after 10 and after 14
    assert nim["residual_refreshes"] == 1 and 0 < nim["lazy_refreshes"] <= 16 - 10
    assert nim["residual_bytes"] == n * cam.height * cam.width * 3
    assert math.isfinite(res["psnr"]) and 0 < res["ssim"] <= 1 and _finite_state(t.method)
    strips = sorted((tmp_path / "run" / "decomposition").glob("*.png"))
    assert [p.stem for p in strips] == [v.stem for v in hazy.train_views]
    import cv2

    assert cv2.imread(str(strips[0])).shape == (cam.height, 5 * cam.width, 3)
    assert len(list((tmp_path / "run" / "extinction").glob("beta_*.png"))) == 5
    assert sorted(p.stem for p in (tmp_path / "run" / "renders" / "test").iterdir()) == \
        sorted(v.stem for v in hazy.test_views)
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    assert any(r.get("event") == "components" and r["iteration"] == 6 for r in log)
    saved = json.loads((tmp_path / "run" / "results.json").read_text())
    assert saved["nimbus"]["components"] == ["csm", "plm", "ggs"]


def test_scored_render_is_the_clean_image(hazy, tmp_path):
    m = _nimbus(hazy, _cfg(iterations=8), tmp_path / "run").method
    camera = m.train_views[0].camera
    with torch.no_grad():
        render = m.render(camera)  # what the runner scores: render["rgb"]
        parts = m.render(camera, view_index=0)
    assert torch.equal(parts["rgb"], render["rgb"])  # the decomposition's extras leave the scored image alone
    assert not torch.allclose(parts["degraded"], render["rgb"])  # the medium is applied in training only
    assert set(parts) >= {"rgb", "depth", "alpha", "transmission", "airlight", "residual", "degraded"}


def test_medium_is_the_same_with_the_compiled_and_the_torch_march(hazy, tmp_path, monkeypatch):
    import dataclasses

    from nimbus.kernels import march as march_kernel

    if not march_kernel.available():
        pytest.skip("compiled kernel unavailable (see tests/test_march_cpp.py)")
    calls = []
    kernel = march_kernel.grid_optical_depth
    monkeypatch.setattr(march_kernel, "grid_optical_depth", lambda *a: calls.append(1) or kernel(*a))
    t = _nimbus(hazy, _cfg(), tmp_path / "run").method
    with torch.no_grad():
        render = t.render(t.train_views[0].camera)
    out = {}
    medium = t.medium
    for backend in ("auto", "torch"):  # auto: the compiled march; torch: grid_sample
        medium.cfg = dataclasses.replace(medium.cfg, backend=backend)
        medium.field.zero_grad(set_to_none=True)
        T, P = medium.forward(t._rays_for(0), render, t.descriptors[0])
        (T.sum() + P.sum()).backward()
        out[backend] = (T.detach(), P.detach(), medium.field.features.grad.clone(),
                        medium.field.log_scale.grad.clone())
    assert len(calls) == 1  # the auto pass, not the torch one
    assert float(out["torch"][0].min()) < 0.99 and float(out["torch"][2].abs().max()) > 0
    for a, b in zip(out["auto"], out["torch"]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_auto_picks_the_components_each_scene_needs(clean, hazy, rainy, tmp_path):
    cfg = _cfg(components="auto", iterations=41, m_init=40, write_decomposition=False, **SEPARATING_THRESHOLDS)
    picked = {}
    for name, scene in (("clean", clean), ("hazy", hazy), ("rainy", rainy)):
        t = _nimbus(scene, cfg, tmp_path / name)
        if name == "clean":  # a haze-free scene never builds the grid, the airlight or their optimiser
            assert t.method.medium is None
        res = t.run()
        picked[name] = res["components"]
        nim = res["nimbus"]
        assert nim["mode"] == "auto" and nim["haze_evidence"]["dark_median"] >= 0
        assert nim["particle_evidence"] is not None
        # A scene declared hazy is judged by the haze pair of particle thresholds, and the record says which.
        ev, hazy = nim["particle_evidence"], nim["haze_evidence"]["present"]
        assert ev["hazy"] == hazy == (name == "hazy")
        assert (ev["asymmetry_threshold"], ev["energy_threshold"]) == particle_thresholds(cfg, hazy)
        if name == "clean":
            assert t.method.particulate is None and nim["residual_refreshes"] == 0 and "csm_forward_s" not in nim["time_s"]
            assert nim["estimated_time_saved_s"]["csm_ray_march_s"] > 0
            assert "plm_refresh_s" in nim["estimated_time_saved_s"]
    assert picked == {"clean": [], "hazy": ["csm", "ggs"], "rainy": ["plm", "ggs"]}


def test_ggs_rescales_gradients_and_densification_statistics(hazy, tmp_path):
    runner = _nimbus(hazy, _cfg(iterations=12, m_init=2), tmp_path / "run")
    runner.run()  # ends in stage 2
    t = runner.method
    vi, view = 0, t.train_views[0]
    step = t.cfg.m_init + 1
    gt = t.train_images[vi]

    def backward(fold: bool):
        """One step's backward and GGS, with the weights folded into the rasterizer's backward or not."""
        for group in t.param_groups():  # the Gaussians' and the medium's
            for p in group["params"]:
                p.grad = None
        render = t.render(view.camera)
        loss, pred = t.loss(step, vi, render, gt)
        t.before_backward(step, vi, render, pred, gt)
        if not fold:
            render["meta"]["row_scale"].weights = None  # as a backend without the fold: GGS scales afterwards
        loss.backward()
        meta = render["meta"]
        info = {"means2d_grad": means2d_grad(meta), "radii": meta["radii"], "visible": meta["visible"],
                "width": view.camera.width, "height": view.camera.height}
        t.reweight_gradients(step, vi, render, pred, gt, info)
        return render, pred, info, {k: v.grad.clone() for k, v in t.params.tensors.items()}

    # Reference: the unscaled gradients of the same step (GGS off), and the weights GGS computes.
    t.use_ggs = False
    render, pred, _, grads = backward(fold=False)
    t.use_ggs = True
    meta = render["meta"]
    w, _ = ggs_weights(meta["depths"], meta["radii"], meta["means2d"].detach(), (pred - gt).abs().sum(-1),
                       meta["visible"], t.ggs)
    assert not torch.allclose(w, torch.ones_like(w))
    # Scaled afterwards (the pass with the guard's check), or by the rasterizer's backward: the same bits.
    _, _, _, after = backward(fold=False)
    assert t._checked_grads is not None
    render, pred, info, folded = backward(fold=True)
    meta = render["meta"]
    assert meta["row_scale"].applied == 1 and t._checked_grads is None
    for name in grads:
        assert torch.equal(after[name], folded[name]), name
    torch.testing.assert_close(folded["means"], grads["means"] * w[:, None], rtol=0, atol=0)
    torch.testing.assert_close(folded["sh_dc"], grads["sh_dc"] * w[:, None, None], rtol=0, atol=0)
    torch.testing.assert_close(info["grad2d_weight"], w)
    # The strategy accumulates the weighted statistic (densifying later, not at this step; no reset).
    strategy = dataclasses.replace(t.strategy, densify_from=step, densify_until=10**9, opacity_reset_interval=10**9)
    plain, weighted = strategy.initialize_state(), strategy.initialize_state()
    unweighted = {k: v for k, v in info.items() if k != "grad2d_weight"}
    assert strategy.step_post_backward(t.params, plain, step, unweighted, t.gen) == []
    assert strategy.step_post_backward(t.params, weighted, step, info, t.gen) == []
    ndc = ndc_grad_norm(means2d_grad(meta), view.camera.width, view.camera.height)
    vis = meta["visible"]
    torch.testing.assert_close(weighted["grad_accum"][vis], plain["grad_accum"][vis] + (w[vis] - 1) * ndc[vis])
    # The guard checks every gradient, whichever way GGS scaled them (its pass checks what it scaled).
    medium = [p for group in t.medium.param_groups() for p in group["params"] if p.grad is not None]
    assert medium
    for fold in (True, False):
        for poisoned in ("sh_dc", "medium"):
            backward(fold)
            assert t._grads_finite() and t._checked_grads is None
            target = t.params["sh_dc"] if poisoned == "sh_dc" else medium[0]
            target.grad.view(-1)[0] = float("nan")
            assert not t._grads_finite(), (fold, poisoned)


def _constant_scene(scene, value):
    views = [View(v.name, v.camera, image=np.full_like(v.image, value), depth=v.depth) for v in scene.views]
    return scene.with_views(views)


@pytest.mark.parametrize("case", ["white", "black", "dense_haze", "single_view"])
def test_extremes_stay_finite_or_stop_clearly(case, clean, tmp_path):
    scene = {"white": lambda: _constant_scene(clean, 1.0), "black": lambda: _constant_scene(clean, 0.0),
             "dense_haze": lambda: _degrade(clean, beta=3.0),
             "single_view": lambda: clean.with_views(clean.train_views[:1]).with_split([])}[case]()
    cfg = _cfg(iterations=10, m_init=4, init_transmission=0.01 if case == "dense_haze" else 0.0)
    runner = _nimbus(scene, cfg, tmp_path / case)
    t = runner.method
    try:
        res = runner.run()
    except NimbusError as e:  # allowed: a clear stop (e.g. everything pruned on a blank input)
        assert "Gaussian" in str(e) or "loss" in str(e)
        return
    assert math.isfinite(res["psnr"]) or res["psnr"] == float("inf")
    assert _finite_state(t)
    if case == "dense_haze":
        with torch.no_grad():
            parts = t.compose(0, t.render(t.train_views[0].camera))
        assert float(parts["T"].median()) < 0.1 and torch.isfinite(parts["con"]).all()


def test_every_gaussian_pruned_stops_cleanly(hazy, tmp_path):
    with pytest.raises(NimbusError, match="every Gaussian was pruned"):
        _nimbus(hazy, _cfg(prune_opacity=0.999), tmp_path / "empty").run()


@pytest.mark.parametrize("refresh", ["lazy", "all"])
def test_resume_continues_to_the_same_result(refresh, hazy, tmp_path):
    cfg = _cfg(write_decomposition=False, refresh_mode=refresh)
    full = _nimbus(hazy, cfg, tmp_path / "full", seed=1).run()

    half = _nimbus(hazy, cfg, tmp_path / "half", seed=1)
    step = half.method.train_iteration

    def interrupted(it):
        if it == 10:  # Ctrl-C in stage 2 after step 9 (the interrupt saves the state); a refresh is due at 10
            raise KeyboardInterrupt
        return step(it)

    half.method.train_iteration = interrupted
    with pytest.raises(KeyboardInterrupt):
        half.run()
    resumed = _nimbus(hazy, cfg, tmp_path / "half", seed=1)
    resumed.load_checkpoint(tmp_path / "half" / CHECKPOINT)
    m = resumed.method
    assert resumed.iteration == 9 and m.particulate is not None and m.medium.field is not None
    out = resumed.run()
    assert out["num_gaussians"] == full["num_gaussians"]
    assert out["psnr"] == pytest.approx(full["psnr"], abs=1e-4)
    assert out["nimbus"]["residual_refreshes"] == full["nimbus"]["residual_refreshes"]
    assert out["nimbus"]["lazy_refreshes"] == full["nimbus"]["lazy_refreshes"]


@pytest.mark.parametrize("variant", [dict(extinction="gaussian"), dict(extinction="uniform", airlight="sh"),
                                     dict(residual_source="restored", airlight="constant"),
                                     dict(refresh_mode="lazy", dcp_stage2=True, lambda_tv=0.0)])
def test_paper_variants_train(variant, hazy, tmp_path):
    runner = _nimbus(hazy, _cfg(iterations=10, m_init=4, **variant), tmp_path / "v")
    res = runner.run()
    t = runner.method
    assert math.isfinite(res["psnr"]) and _finite_state(t)
    if variant.get("extinction") == "gaussian":
        assert "extinction_logit" in t.params.tensors and t.medium.field is None
        assert t.params["extinction_logit"].shape[0] == len(t.params)
    if variant.get("refresh_mode") == "lazy":
        assert res["nimbus"]["lazy_refreshes"] > 0 and res["nimbus"]["residual_refreshes"] == 1


def test_lazy_refresh_checks_consistency_against_the_neighbours_last_surfaces(rainy, tmp_path):
    """``refresh_mode=lazy`` re-extracts a view's R from the step's own render, with the view-consistency check
    run against each neighbour's surface from when it was last rendered: with every surface current it gives
    exactly the R that a full refresh (every view re-rendered) gives."""
    from nimbus.methods.gs3d import GaussianSplatting

    runner = _nimbus(rainy, _cfg(iterations=12, m_init=4, refresh_mode="lazy"), tmp_path / "lazy")
    res = runner.run()
    m = runner.method
    assert res["nimbus"]["lazy_refreshes"] > 0 and res["nimbus"]["residual_refreshes"] == 1
    assert m._consistency_check() is not None and len(m._surfaces) == len(rainy.train_views)
    step = runner.iteration
    _, surfaces = m._composites(step)
    for vi in (0, len(surfaces) - 1):
        m._surfaces = list(surfaces)
        render = GaussianSplatting.render(m, m.train_views[vi].camera, m.active_sh_degree(step))
        m.particulate.store.stamps[vi] = -1  # stale: the next use refreshes it
        m._lazy_refresh(step, vi, render, m.compose(vi, render)["con"])
        lazy = m.particulate.store.get(vi).clone()
        assert m.particulate.store.stamps[vi] == step and lazy.sum() > 0
        m._refresh_all(step)
        assert torch.equal(m.particulate.store.get(vi), lazy)


def test_cli_trains_a_named_variant(tmp_path):
    from nimbus.cli.train import _main

    out = tmp_path / "cli"
    assert _main(["builtin:garden:tiny", "--method", "nimbus-no-ggs", "--preset", "tiny", "--set", "iterations=4",
                  "--set", "m_init=2", "--set", "write_decomposition=false", "--out", str(out), "--quiet"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["method"] == "nimbus-no-ggs" and res["components"] == ["csm", "plm"]
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["method"] == "nimbus-no-ggs" and cfg["config"]["m_init"] == 2


def test_unclipped_ggs_is_written_as_strict_json_and_read_back(tmp_path):
    """nimbus-paper's ggs_clip=(0, inf) is a setting: config.json spells it "inf" (strict JSON, which
    Python's default Infinity token is not), and opening the run gives the infinite clip back."""
    import math

    from nimbus.cli.train import _main
    from nimbus.train.runner import Runner

    out = tmp_path / "unclipped"
    assert _main(["builtin:garden:tiny", "--method", "nimbus-full", "--preset", "tiny", "--set", "iterations=4",
                  "--set", "m_init=2", "--set", "write_decomposition=false", "--set", "ggs_clip=0,inf",
                  "--out", str(out), "--quiet"]) == 0
    text = (out / "config.json").read_text()
    cfg = json.loads(text, parse_constant=lambda token: pytest.fail(f"non-strict JSON token {token}"))
    assert cfg["config"]["ggs_clip"] == [0.0, "inf"]
    assert Runner.open(out, progress=False).cfg.ggs_clip == (0.0, math.inf)


def test_cli_components_flag_forces_components_and_rejects_misuse(tmp_path, capsys):
    from nimbus.cli.train import _main, main

    base = ["builtin:garden:tiny", "--preset", "tiny", "--set", "iterations=4", "--set", "m_init=2",
            "--set", "write_decomposition=false", "--quiet"]
    out = tmp_path / "forced"
    assert _main([*base, "--method", "nimbus", "--components", "plm,ggs", "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["components"] == ["plm", "ggs"] and res["nimbus"]["mode"] != "auto"
    assert json.loads((out / "config.json").read_text())["config"]["components"] == "plm,ggs"
    bad = [
        ([*base, "--method", "3dgs", "--components", "csm"], "applies to NimbusGS methods"),
        ([*base, "--method", "nimbus", "--components", "csm", "--set", "components=plm"], "once"),
        ([*base, "--method", "nimbus", "--components", "fog"], "unknown fog"),
        (["--resume", str(out), "--components", "csm"], "saved settings"),
    ]
    for i, (argv, message) in enumerate(bad):
        target = tmp_path / f"bad{i}"
        with pytest.raises(SystemExit) as exit_info:
            main([*argv, "--out", str(target)] if "--resume" not in argv else argv)
        err = capsys.readouterr().err
        assert exit_info.value.code != 0 and message in err, err
        assert not target.exists()


@pytest.mark.slow
@pytest.mark.parametrize("setting", ["haze", "particles"])
def test_nimbus_beats_3dgs_on_degraded_views(setting, hazy, rainy, tmp_path):
    """Same iterations, same schedule: NimbusGS scores higher than 3DGS on the clean test views."""
    scene = hazy if setting == "haze" else rainy
    # The 32 x 24 test scenes are told apart at SEPARATING_THRESHOLDS (the defaults are derived at the tiny size).
    cfg = _cfg(components="auto", iterations=300, m_init=120, refresh_interval=60, densify_from=100,
               densify_until=240, densify_interval=50, grid_resolution=16, ray_samples=16, write_decomposition=False,
               **SEPARATING_THRESHOLDS)
    nimbus = _nimbus(scene, cfg, tmp_path / "nimbus").run()
    gs_cfg = dict((f, getattr(cfg, f)) for f in ("iterations", "sh_degree", "sh_degree_interval", "densify_from",
                                                  "densify_until", "densify_interval", "opacity_reset_interval"))
    from nimbus.train.config import TrainConfig

    gs = Runner("3dgs", scene, TrainConfig(**gs_cfg), tmp_path / "3dgs", seed=0, progress=False).run()
    expected = ["csm", "ggs"] if setting == "haze" else ["plm", "ggs"]
    assert nimbus["components"] == expected
    # Measured margins: about +4.8 dB (haze) and +1.5 dB (streaks).
    assert nimbus["psnr"] > gs["psnr"] + (3.0 if setting == "haze" else 0.5)


def test_initial_colours_are_dehazed_through_the_initial_medium(hazy, tmp_path):
    """init_dehaze: colour = (c - A0 (1 - T0)) / max(T0, 0.1), T0 the initial medium's transmission from the
    cameras that see the Gaussian (median), through the box."""
    from nimbus.render.sh import sh_to_rgb

    plain = _nimbus(hazy, _cfg(init_dehaze=False), tmp_path / "plain").method
    dehazed = _nimbus(hazy, _cfg(init_dehaze=True), tmp_path / "dehazed").method
    means = plain.params.tensors["means"].detach().double()
    beta0 = math.log(2.0) * plain.medium.initial_density_scale
    lo, hi = (np.array(b) for b in (plain.medium.box.lo, plain.medium.box.hi))
    checked = 0
    for i in range(0, means.shape[0], max(1, means.shape[0] // 25)):
        p = means[i].numpy()
        if not ((p > lo) & (p < hi)).all():
            continue
        taus = []
        for v in plain.train_views:
            cam = v.camera
            uv, z = cam.project(p[None])
            if z[0] > plain.cfg.near_plane and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height:
                # Inside a convex box with the camera inside too, the whole segment past the near bound counts.
                if ((cam.center > lo) & (cam.center < hi)).all():
                    taus.append(beta0 * (np.linalg.norm(p - cam.center) - plain.cfg.near_plane))
        if not taus:
            continue
        T0 = math.exp(-float(torch.tensor(taus).median()))  # torch's median: the lower middle, as nanmedian
        a0 = plain.descriptors[:, :3].mean(0).double()
        c = sh_to_rgb(plain.params.tensors["sh_dc"][i, 0].double())
        expected = ((c - a0 * (1 - T0)) / max(T0, 0.1)).clamp(0, 1)
        got = sh_to_rgb(dehazed.params.tensors["sh_dc"][i, 0].double())
        torch.testing.assert_close(got, expected, atol=2e-4, rtol=0)
        checked += 1
    assert checked >= 5
    # The dehazed start is darker than the hazy colours (haze adds airlight).
    mean_rgb = {k: float(sh_to_rgb(t.params.tensors["sh_dc"].detach()).mean()) for k, t in (("plain", plain),
                                                                                          ("dehazed", dehazed))}
    assert mean_rgb["dehazed"] < mean_rgb["plain"] - 0.02


def test_dehazed_view_prior_is_each_views_dark_channel_dehaze_and_only_with_csm(hazy, tmp_path):
    from nimbus.restore import pixel_sizes
    from nimbus.restore.classical import dehaze

    m = _nimbus(hazy, _cfg(), tmp_path / "on").method
    assert len(m.prior_clean) == len(m.train_views)
    for img, prior in zip(m.train_images, m.prior_clean):
        torch.testing.assert_close(prior, dehaze(img.float(), pixel_sizes(*img.shape[:2])[0])[0], rtol=0, atol=0)
    # The dehaze removes airlight: the prior is darker than the hazy view it was made from.
    assert float(torch.stack(m.prior_clean).mean()) < float(torch.stack(m.train_images).mean()) - 0.05
    assert _nimbus(hazy, _cfg(components="plm,ggs"), tmp_path / "no-csm").method.prior_clean is None
    assert _nimbus(hazy, _cfg(lambda_dehaze=0.0), tmp_path / "off").method.prior_clean is None


def test_dehazed_view_prior_adds_the_photometric_loss_at_its_stage_weight(hazy, tmp_path):
    from nimbus.methods.nimbusgs.losses import stage_loss

    m = _nimbus(hazy, _cfg(lambda_dehaze=0.7, prior_stage2=0.5, components="csm"), tmp_path / "run").method
    vi = 1
    gt = m.train_images[vi]
    with torch.no_grad():
        render = m.render(m.train_views[vi].camera)
        term = float(stage_loss(render["rgb"], m.prior_clean[vi], m.cfg.lambda_dssim, None))
        assert term > 0
        for step, weight in ((1, 0.7), (m.cfg.m_init + 1, 0.35)):
            with_prior = float(m.loss(step, vi, render, gt)[0])
            prior, m.prior_clean = m.prior_clean, None
            without = float(m.loss(step, vi, render, gt)[0])
            m.prior_clean = prior
            assert with_prior - without == pytest.approx(weight * term, rel=1e-5)


def test_dehazed_view_prior_on_surfaces_only_leaves_the_sky_out(hazy, tmp_path, monkeypatch):
    from nimbus.methods.nimbusgs.losses import stage_loss

    m = _nimbus(hazy, _cfg(lambda_dehaze=1.0, components="csm", prior_surface_only=True), tmp_path / "run").method
    vi = 1
    gt = m.train_images[vi]
    with torch.no_grad():
        render = m.render(m.train_views[vi].camera)
        m.loss(1, vi, render, gt)  # the first call sets stage 1 up; the figures below compare later calls
        h, w = gt.shape[:2]
        surface = torch.zeros(h, w, dtype=torch.bool)
        surface[: h // 2] = True  # the top half "reaches a surface", the rest is "sky"
        monkeypatch.setattr(m.medium, "surface_mask", lambda rays, r: surface)
        with_prior = float(m.loss(1, vi, render, gt)[0])
        prior, m.prior_clean = m.prior_clean, None
        without = float(m.loss(1, vi, render, gt)[0])
        m.prior_clean = prior
        clean = m.compose(vi, render)["clean"]
        term = float(stage_loss(clean, prior[vi], m.cfg.lambda_dssim, surface))
        assert with_prior - without == pytest.approx(term, rel=1e-5)
        assert term != pytest.approx(float(stage_loss(clean, prior[vi], m.cfg.lambda_dssim, None)), rel=1e-3)
        monkeypatch.setattr(m.medium, "surface_mask", lambda rays, r: torch.zeros_like(surface))
        assert float(m.loss(1, vi, render, gt)[0]) != pytest.approx(with_prior, rel=1e-3)
        m.prior_clean = None
        all_sky_without = float(m.loss(1, vi, render, gt)[0])
        m.prior_clean = prior
        assert float(m.loss(1, vi, render, gt)[0]) == pytest.approx(all_sky_without, rel=1e-6)  # no prior term


def test_prior_moments_are_kept_per_view_and_change_no_bit(hazy, tmp_path, monkeypatch):
    import nimbus.methods.nimbusgs.method as nimbus_method

    runner = _nimbus(hazy, _cfg(iterations=4, m_init=2), tmp_path / "run")
    runner.run()
    t = runner.method
    assert t.prior_clean is not None and t._prior_cache  # training used the prior and kept its moments
    vi, view = 1, t.train_views[1]
    step = t.cfg.m_init + 1
    render = t.render(view.camera)
    kept = t.loss(step, vi, render, t.train_images[vi])[0]
    assert t._prior_cache[vi] is not None
    monkeypatch.setattr(nimbus_method, "PRIOR_MOMENTS_BUDGET", 0)
    t._prior_cache.clear()
    fresh = t.loss(step, vi, render, t.train_images[vi])[0]
    assert t._prior_cache == {vi: None}  # past the budget: filtered at every step
    assert torch.equal(kept, fresh)
    g_kept = torch.autograd.grad(kept, render["rgb"], retain_graph=True)[0]
    g_fresh = torch.autograd.grad(fresh, render["rgb"])[0]
    assert torch.equal(g_kept, g_fresh)
