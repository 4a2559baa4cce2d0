"""restore-3dgs: the 2D restorers (dehazing, particle removal, auto, ONNX) and the method through the runner."""

import json

import numpy as np
import pytest
import torch

from nimbus.config_set import apply_overrides
from nimbus.data.builtin import render_builtin
from nimbus.errors import NimbusError
from nimbus.methods.registry import get_method
from nimbus.restore import Restorer, image_evidence, parse_restorer
from nimbus.restore.classical import ParticleConfig, RestoreConfig, dehaze, remove_particles
from nimbus.train.runner import Runner


def _texture(h=96, w=128, seed=0):
    """A textured image with a dark channel near 0 (He's prior): per-pixel colours with one channel dark."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.2, 0.9, (h, w, 3)).astype(np.float32)
    img = np.asarray(__import__("cv2").GaussianBlur(img, (0, 0), 1.5), np.float32)
    dark = rng.integers(0, 3, (h // 8, w // 8)).repeat(8, 0).repeat(8, 1)
    np.put_along_axis(img, dark[..., None], 0.02, axis=-1)
    return img


def _streaks(img, n=40, seed=1, amplitude=0.7):
    """``img`` with ``n`` one-pixel-wide bright streaks (slanted, 6 to 20 px long)."""
    rng = np.random.default_rng(seed)
    out = img.copy()
    h, w = img.shape[:2]
    for _ in range(n):
        x, y, length = rng.integers(0, w), rng.integers(0, h), rng.integers(6, 20)
        ys = np.arange(y, min(h, y + length))
        out[ys, np.clip(x + (ys - y) // 4, 0, w - 1)] += amplitude
    return np.clip(out, 0, 1).astype(np.float32)


def _haze(img, t=0.45, airlight=(0.8, 0.82, 0.85)):
    a = np.asarray(airlight, np.float32)
    return (img * t + a * (1 - t)).astype(np.float32)


# --- dehazing ---------------------------------------------------------------------------
def test_dcp_inverts_a_known_constant_depth_haze():
    # A textured wall at one depth under a sky band (rows 0..15, J = A: the haziest pixels, where He's
    # estimator finds the airlight).
    t, a = 0.45, np.array([0.8, 0.82, 0.85], np.float32)
    clean = _texture()
    clean[:16] = a
    hazy = _haze(clean, t, a)
    cfg = RestoreConfig(median=1, patch=7, smooth=28, refine="guided", omega=1.0)
    restored, t_est, a_est = dehaze(torch.from_numpy(hazy), cfg)
    np.testing.assert_allclose(a_est.numpy(), a, atol=0.01)
    wall = slice(16 + 14, None)  # away from the sky's edge, which the guided filter's window blurs
    assert float(t_est[wall].median()) == pytest.approx(t, abs=0.03)
    err_before = np.abs(hazy - clean)[wall].mean()
    err_after = np.abs(restored.numpy() - clean)[wall].mean()
    assert err_after < 0.03 and err_after < err_before / 5


def test_the_sky_tolerance_keeps_a_bright_sky_from_going_dark():
    # Rows 0..15: the haziest band (J = A, where the airlight is found); rows 16..47: a blue sky, bright in every
    # channel (the dark-channel prior reads it as thick haze); below: a textured wall.  Same haze everywhere.
    t, a = 0.45, np.array([0.8, 0.82, 0.85], np.float32)
    clean = _texture()
    clean[:16] = a
    clean[16:48] = [0.62, 0.72, 0.9]
    hazy = torch.from_numpy(_haze(clean, t, a))
    sky, wall = (slice(24, 40), slice(None)), (slice(64, None), slice(None))

    def err(cfg, where):
        return float(np.abs(dehaze(hazy, cfg)[0].numpy() - clean)[where].mean())

    off = RestoreConfig(median=1, patch=7, smooth=28, refine="guided", sky_tolerance=0.0)
    on = RestoreConfig(median=1, patch=7, smooth=28, refine="guided")
    assert on.sky_tolerance == 0.2  # the default, chosen on the validation views
    assert err(off, sky) > 0.1  # without it, the sky is pushed far too dark
    assert err(on, sky) < err(off, sky) / 2
    assert err(on, wall) < err(off, wall) + 0.01  # the textured wall keeps its restoration
    _, t_on, _ = dehaze(hazy, on)
    assert float(t_on.max()) <= 1.0


def test_classical_restore_keeps_the_box_refinement():
    # NimbusGS's ablation uses the box refinement; guided differs and is a separate choice.
    img = torch.from_numpy(_haze(_texture(48, 64)))
    box, _, _ = dehaze(img, RestoreConfig(patch=7, smooth=15))
    guided, _, _ = dehaze(img, RestoreConfig(patch=7, smooth=15, refine="guided"))
    assert box.shape == guided.shape and not torch.equal(box, guided)
    with pytest.raises(ValueError, match="refinement"):
        dehaze(img, RestoreConfig(refine="bilateral"))


# --- particles --------------------------------------------------------------------------
def _smooth_texture(h=96, w=128, seed=0):
    """Blurred colour noise in [0.1, 0.8] (texture at every scale down to a few pixels)."""
    img = np.random.default_rng(seed).uniform(0, 1, (h, w, 3)).astype(np.float32)
    img = np.asarray(__import__("cv2").GaussianBlur(img, (0, 0), 1.5), np.float32)
    return ((img - img.min()) / (img.max() - img.min()) * 0.7 + 0.1).astype(np.float32)


def test_particle_remover_removes_white_streaks_from_texture():
    clean = _smooth_texture()
    rainy = _streaks(clean)
    out = remove_particles(rainy, ParticleConfig())
    before = np.abs(rainy - clean).mean()
    after = np.abs(out - clean).mean()
    assert after < before / 3
    # Without particles the texture is left nearly as it is.
    assert np.abs(remove_particles(clean) - clean).mean() < 0.2 * before


# --- auto -------------------------------------------------------------------------------
def test_auto_picks_dcp_on_haze_and_particles_on_rain():
    clean = _texture()
    hazy, rainy = _haze(clean), _streaks(clean, n=120)
    assert Restorer("auto")(hazy)[1]["steps"] == ["dcp"]
    assert Restorer("auto")(rainy)[1]["steps"] == ["particles"]
    assert Restorer("auto")(clean)[1]["steps"] == []
    ev = image_evidence(hazy)
    assert ev.haze and not ev.particles and ev.dark_mean > image_evidence(clean).dark_mean


def test_forced_restorers_run_what_they_name():
    img = _streaks(_haze(_texture(48, 64)))
    assert Restorer("dcp")(img)[1]["steps"] == ["dcp"]
    assert Restorer("particles")(img)[1]["steps"] == ["particles"]
    assert Restorer("particles+dcp")(img)[1]["steps"] == ["particles", "dcp"]
    out, info = Restorer("none")(img)
    assert info["steps"] == [] and np.array_equal(out, img)


@pytest.mark.parametrize("spec", ["fog", "dcp+fog", "", "onnx:", "auto+dcp"])
def test_bad_restorer_strings_are_clear_errors(spec):
    with pytest.raises(NimbusError, match="restorer=.*(unknown|needs a model path)"):
        parse_restorer(spec)


def test_restorer_setting_through_set():
    base = get_method("restore-3dgs").preset("tiny")
    assert base.restorer == "auto"
    assert apply_overrides(base, {"restorer": "dcp+particles"}).restorer == "dcp+particles"
    with pytest.raises(NimbusError, match="restorer='smog'"):
        apply_overrides(base, {"restorer": "smog"})


# --- ONNX -------------------------------------------------------------------------------
def _onnx_model(path):
    """A tiny conv net exported to ONNX: out = clip(0.5 * in + 0.25) per channel (a 1x1 conv)."""
    net = torch.nn.Conv2d(3, 3, 1)
    with torch.no_grad():
        net.weight.copy_(0.5 * torch.eye(3)[..., None, None])
        net.bias.fill_(0.25)
    torch.onnx.export(net, torch.rand(1, 3, 16, 16), str(path), input_names=["image"], output_names=["restored"],
                      dynamic_axes={"image": {2: "h", 3: "w"}, "restored": {2: "h", 3: "w"}}, dynamo=False)
    return path


def test_onnx_restorer_runs_the_users_model(tmp_path):
    pytest.importorskip("onnx")
    path = _onnx_model(tmp_path / "restorer.onnx")
    img = _texture(24, 40)
    out, info = Restorer(f"onnx:{path}")(img)
    assert info["steps"] == ["onnx"] and out.shape == img.shape and out.dtype == np.float32
    np.testing.assert_allclose(out, 0.5 * img + 0.25, atol=1e-5)
    assert Restorer(f"onnx:{path}").describe()["model_sha256"]


def test_missing_or_corrupt_onnx_is_one_clear_error(tmp_path):
    with pytest.raises(NimbusError, match="does not exist"):
        Restorer(f"onnx:{tmp_path / 'missing.onnx'}")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(NimbusError, match="could not be loaded"):
        Restorer(f"onnx:{tmp_path / 'junk.onnx'}")


# --- the method -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def hazy_scene():
    """The tiny built-in garden, its training views in constant haze (t = 0.5)."""
    scene = render_builtin("garden", size="tiny", seed=0)
    views = [v if v.name in scene.test_names else
             type(v)(v.name, v.camera, image=_haze(v.image, 0.5), depth=v.depth) for v in scene.views]
    return scene.with_views(views)


def _config(**kw):
    cfg = get_method("restore-3dgs").preset("tiny")
    return apply_overrides(cfg, {"iterations": "12", "checkpoint_interval": "6", **kw})


def test_trains_on_restored_views_through_the_runner_and_resumes(hazy_scene, tmp_path, interrupt_and_resume):
    full = Runner("restore-3dgs", hazy_scene, _config(), tmp_path / "full", seed=1, progress=False,
                  device=torch.device("cpu"))
    method = full.method
    # The training images are the restored ones: auto dehazed every (hazy) view.
    assert all("dcp" in steps for steps in method.restored_steps.values())
    restored, _ = Restorer("auto")(method.train_views[0].load_image())
    np.testing.assert_array_equal(method.train_images[0].cpu().numpy(), restored)
    full_out = full.run()

    # Ctrl-C after step 7, between the checkpoints at 6 and 12
    resumed = interrupt_and_resume(lambda: Runner("restore-3dgs", hazy_scene, _config(), tmp_path / "half", seed=1,
                                                  progress=False, device=torch.device("cpu")), 7)
    assert resumed.iteration == 7
    out = resumed.run()
    assert out["psnr"] == full_out["psnr"] and out["ssim"] == full_out["ssim"]
    views = out["restore"]["views"]
    assert out["restore"]["restorer"] == "auto" and sum(views.values()) == len(hazy_scene.train_views)
    log = [json.loads(line) for line in (tmp_path / "half" / "train_log.jsonl").read_text().splitlines()]
    assert [r["views"] for r in log if r.get("event") == "restored"] == [views]


def test_restore_3dgs_is_a_method_of_nimbus_train(tmp_path):
    from nimbus.cli.train import _main as train_main

    out = tmp_path / "cli"
    args = ["--set", "iterations=4", "--set", "checkpoint_interval=2", "--set", "restorer=particles", "--quiet"]
    assert train_main(["builtin:garden:tiny", "--method", "restore-3dgs", "--preset", "tiny", *args,
                       "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["config"]["restorer"] == "particles"
    assert train_main(["--resume", str(out), "--quiet"]) == 0
    assert json.loads((out / "results.json").read_text())["restore"]["restorer"] == "particles"


def test_a_missing_onnx_model_stops_the_method_at_construction(hazy_scene, tmp_path):
    with pytest.raises(NimbusError, match="does not exist"):
        Runner("restore-3dgs", hazy_scene, _config(restorer=f"onnx:{tmp_path / 'nope.onnx'}"), tmp_path / "r",
               progress=False, device=torch.device("cpu"))
