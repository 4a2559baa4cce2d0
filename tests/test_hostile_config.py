"""Hostile config values (issue 14, items 6 and 7): every numeric setting is checked at the boundary.

Before, ``--set lr_means_init=inf`` finished with NaN Gaussians and exit 0, ``near_plane=nan``
trained on nothing, and ``haze.beta_range=[1]``, ``checkpoint_interval=0``, ``log_interval=0``
and ``background=0.5`` ended in tracebacks.  Now each is one ``error:`` line naming the key,
the value as typed and what is accepted, and nothing is written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from nimbus.config_set import apply_overrides, parse_set_args
from nimbus.config_validation import INT_MAX, field_shapes, at_least, field_problem, validate
from nimbus.errors import NimbusError
from nimbus.methods.nimbusgs.config import NimbusConfig
from nimbus.methods.nimbusgs.config import PRESETS as NIMBUS_PRESETS
from nimbus.train.config import PRESETS as GS_PRESETS
from nimbus.train.config import TrainConfig
from nimbus.methods.registry import METHODS, get_method
from weather_synth.config import SynthConfig, protocol_config


def _numeric_fields(cls):
    """(name, shape) of every int / float field (scalars and fixed-length tuples) of a config class."""
    return [(n, s) for n, s in field_shapes(cls).items() if s.base in (int, float) and s.length is not None]


def _synth_leaves():
    """(dotted key, owning class, field name) of every numeric leaf of the synthesizer's config tree."""
    root = protocol_config()
    out = [(n, SynthConfig, n) for n, _ in _numeric_fields(SynthConfig)]
    for group in ("haze", "rain", "snow", "depth", "compose"):
        cls = type(getattr(root, group))
        out += [(f"{group}.{n}", cls, n) for n, _ in _numeric_fields(cls)]
    return out


# --- nimbus-train: TrainConfig / NimbusConfig -------------------------------------------------------
@pytest.mark.parametrize("key, raw, accepted", [
    ("near_plane", "nan", "a finite number > 0"),
    ("lr_means_init", "inf", "a finite number > 0"),
    ("lr_means_final", "0", "a finite number > 0"),
    ("checkpoint_interval", "0", "an integer >= 1"),
    ("log_interval", "0", "an integer >= 1"),
    ("background", "0.5", "3 items each a number in [0, 1]"),
    ("background", "0.5,0.5,abc", "3 items each a number in [0, 1]"),
    ("background", "0,0,2", "3 items each a number in [0, 1]"),
    ("iterations", "2.5", "an integer >= "),  # 1 for 3DGS, 2 for NimbusGS
    ("iterations", "many", "an integer >= "),  # 1 for 3DGS, 2 for NimbusGS
    ("iterations", "0", "an integer >= "),  # 1 for 3DGS, 2 for NimbusGS
    ("sh_degree", "4", "an integer in 0..3"),
    ("init_opacity", "1", "a number in (0, 1)"),
    ("opacity_reset_value", "0", "a number in (0, 1)"),
    ("max_gaussians", "1e12", f"an integer >= 1 and at most {INT_MAX}"),
    ("test_interval", "-1", "an integer >= 0"),
    ("lambda_dssim", "nan", "a number in [0, 1]"),
    ("adam_eps", "-inf", "a finite number > 0"),
    ("random_background", "maybe", "true or false"),
    ("backend", "tpu", "one of auto, torch, cpp, gsplat"),
])
def test_bad_trainer_set_value_names_key_value_and_range(key, raw, accepted):
    for presets in (GS_PRESETS, NIMBUS_PRESETS):
        with pytest.raises(NimbusError) as e:
            apply_overrides(presets["tiny"], {key: raw})
        assert str(e.value).startswith(f"--set {key}={raw}: must be {accepted}")


@pytest.mark.parametrize("key, raw, accepted", [
    ("ggs_clip", "1", "(lo, hi), 2 items"),
    ("ggs_clip", "3,2", "with lo <= hi"),
    ("ggs_clip", "nan,2", "(lo, hi), 2 items"),
    ("box_content_factor", "0.5", "0 or a finite number >= 1"),
    ("grid_resolution", "1", "an integer >= 2"),
    ("ray_samples", "0", "an integer >= 1"),
    ("refresh_interval", "0", "an integer >= 1"),
    ("init_transmission", "1", "a number in [0, 1)"),
    ("ggs_r0", "0", "a finite number > 0"),
    ("auto_depth_corr", "nan", "a number in [-1, 1]"),
    ("extinction", "voxels", "one of grid, uniform, gaussian"),
    ("iterations", "1", "an integer >= 2 (stage 1 and stage 2 need one each)"),
])
def test_bad_nimbusgs_set_value_names_key_value_and_range(key, raw, accepted):
    with pytest.raises(NimbusError) as e:
        apply_overrides(NIMBUS_PRESETS["tiny"], {key: raw})
    assert str(e.value).startswith(f"--set {key}={raw}: must be ") and accepted in str(e.value)


def test_tuple_errors_show_the_syntax_to_use():
    with pytest.raises(NimbusError, match=r"e\.g\. background=0\.0,0\.0,0\.0$"):
        apply_overrides(GS_PRESETS["tiny"], {"background": "0.5"})


@pytest.mark.parametrize("cls", [TrainConfig, NimbusConfig])
def test_every_numeric_trainer_field_refuses_nan_and_inf_on_construction(cls):
    base = NIMBUS_PRESETS["tiny"] if cls is NimbusConfig else GS_PRESETS["tiny"]
    fields = _numeric_fields(cls)
    assert len(fields) >= (55 if cls is NimbusConfig else 30)  # a guard against the test checking nothing
    for name, shape in fields:
        for bad in (math.nan, -math.inf):
            value = (bad,) * shape.length if shape.length else bad
            with pytest.raises(NimbusError, match=f"^{name}=") as e:
                dataclasses.replace(base, **{name: value})
            assert "must be" in str(e.value), name
        if shape.base is int:
            with pytest.raises(NimbusError, match=f"^{name}=2.5: must be an integer"):
                dataclasses.replace(base, **{name: 2.5})
            with pytest.raises(NimbusError, match="integer"):
                dataclasses.replace(base, **{name: True})


def test_a_config_json_with_nan_is_refused_when_rebuilt():
    # --resume rebuilds the config from config.json; json writes NaN and reads it back.
    saved = json.loads(json.dumps(dataclasses.asdict(dataclasses.replace(NIMBUS_PRESETS["tiny"]))))
    saved["near_plane"] = float("nan")
    with pytest.raises(NimbusError, match="near_plane=nan: must be a finite number > 0"):
        NimbusConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()})


def test_presets_variants_and_extreme_but_valid_values_still_construct():
    for name in sorted(METHODS):
        for p in ("tiny", "fast", "paper"):
            config = get_method(name).preset(p)
            validate(config, config.LIMITS)
    tiny = NIMBUS_PRESETS["tiny"]
    # the stability report's extreme-but-legal settings, and the ablations' off switches
    ok = apply_overrides(tiny, {"init_opacity": "1e-4", "lr_scales": "50", "near_plane": "1e6", "ggs_clip": "0,inf",
                              "box_content_factor": "0", "lambda_dcp": "0", "lambda_tv": "0", "test_interval": "0",
                              "background": "1,1,1", "consistency_neighbours": "0", "dcp_temperature": "0"})
    assert ok.ggs_clip == (0.0, math.inf) and ok.background == (1.0, 1.0, 1.0)
    assert apply_overrides(GS_PRESETS["tiny"], {"iterations": "1e3"}).iterations == 1000
    # stretching the tiny schedule 10x keeps its "never" opacity reset (10**9) a legal integer
    longer = apply_overrides(GS_PRESETS["tiny"], {"iterations": "3000"})
    assert longer.opacity_reset_interval == INT_MAX and longer.densify_until == 10 * GS_PRESETS["tiny"].densify_until


def test_a_numeric_field_without_a_limit_is_a_programming_error():
    @dataclasses.dataclass(frozen=True)
    class Half:
        count: int = 1
        scale: float = 1.0

    assert field_problem(Half, "count", 0, {"count": at_least(1)}) == "must be an integer >= 1"
    with pytest.raises(TypeError, match="Half.scale is numeric but has no entry"):
        validate(Half(), {"count": at_least(1)})


# --- nimbus-synth: SynthConfig and its sub-configs -----------------------------------------------
@pytest.mark.parametrize("item, accepted", [
    ("haze.beta_range=[1]", "(lo, hi), 2 items each a finite number >= 0, with lo <= hi"),
    ("haze.beta_range=[2, 1]", "with lo <= hi"),
    ("haze.beta_range=[1, Infinity]", "(lo, hi), 2 items each a finite number >= 0"),
    ("haze.beta=abc", "a number >= 0"),
    ("haze.beta=NaN", "a number >= 0"),
    ("haze.airlight=[0.5, 0.5]", "3 items each a number in [0, 1]"),
    ("haze.airlight_range=[0.2, 1.5]", "(lo, hi), 2 items each a number in [0, 1]"),
    ("haze.fog_grid=0", "an integer >= 1"),
    ("haze.mode=fog", "one of onerestore, homogeneous, heterogeneous"),
    ("haze.quantize_depth=2", "true or false"),  # 1 / 0 are true / false, as for the trainer's booleans
    ("rain.slices=2.5", "an integer in 1..64"),
    ("rain.angle_jitter=-Infinity", "a number in [0, 90]"),
    ("snow.color=2", "a number in [0, 1]"),
    ("depth.guided_eps=0", "a finite number > 0"),
    ("compose.snow_color=NaN", "a number in [0, 1]"),
    ("layer_compression=10", "an integer in 0..9"),
    ("seed=-1", "an integer >= 0"),
])
def test_bad_synth_set_value_names_key_value_and_range(item, accepted):
    with pytest.raises(NimbusError) as e:
        apply_overrides(protocol_config(), parse_set_args([item]))
    message = str(e.value)
    assert message.startswith(f"--set {item}: must be ") and accepted in message


def test_synth_set_keeps_its_grammar_and_legal_extremes():
    cfg = apply_overrides(protocol_config(), parse_set_args(["haze.beta=Infinity", "haze.airlight=0.8", "rain.slices=3.0",
                                                             "haze.fog_grid=1e3", "haze.beta_range=[0, 0]"]))
    assert cfg.haze.beta == math.inf and cfg.haze.airlight == 0.8 and cfg.haze.beta_range == (0, 0)
    assert cfg.rain.slices == 3 and isinstance(cfg.rain.slices, int) and cfg.haze.fog_grid == 1000
    assert apply_overrides(cfg, parse_set_args(["haze.beta=null"])).haze.beta is None


def test_every_numeric_synth_leaf_refuses_nan_through_set():
    leaves = _synth_leaves()
    assert len(leaves) >= 30
    for key, cls, name in leaves:
        assert name in cls.LIMITS, key
        shape = field_shapes(cls)[name]
        raw = json.dumps([math.nan] * shape.length) if shape.length else "NaN"
        with pytest.raises(NimbusError, match="must be") as e:
            apply_overrides(protocol_config(), parse_set_args([f"{key}={raw}"]))
        assert str(e.value).startswith(f"--set {key}={raw}: "), key


def test_synth_config_checks_its_whole_tree_on_construction():
    cfg = protocol_config()
    with pytest.raises(NimbusError, match=r"^fog_grid=0: must be an integer >= 1"):
        dataclasses.replace(cfg, haze=dataclasses.replace(cfg.haze, fog_grid=0))
    with pytest.raises(NimbusError, match=r"^max_wind_tilt=nan: must be a number in \[0, 90\)"):
        SynthConfig(max_wind_tilt=math.nan)


def test_a_huge_or_deeply_nested_value_gives_a_short_message():
    with pytest.raises(NimbusError) as e:
        apply_overrides(protocol_config(), parse_set_args(["haze.beta=" + "[" * 100_000]))
    assert len(str(e.value)) < 200 and "(100000 characters)" in str(e.value)
    with pytest.raises(NimbusError) as e:
        apply_overrides(GS_PRESETS["tiny"], {"near_plane": "9" * 5000})  # parses to inf
    assert len(str(e.value)) < 200


# --- the command lines: one error line, exit 2, nothing written ------------------------------------
@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    from nimbus.data.builtin import render_builtin
    from nimbus.data.io import write_scene

    garden = render_builtin("garden", "tiny", seed=0)
    return write_scene(garden.with_views(garden.views[:3]), tmp_path_factory.mktemp("scene") / "garden")


def _run(main, argv, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    return e.value.code, capsys.readouterr().err


@pytest.mark.parametrize("item", ["near_plane=nan", "lr_means_init=inf", "checkpoint_interval=0", "log_interval=0",
                                  "background=0.5", "iterations=abc"])
def test_nimbus_train_bad_set_exits_2_with_one_line_and_no_run_folder(tmp_path, scene_dir, capsys, item):
    from nimbus.cli.train import main

    out = tmp_path / "run"
    for method in ("3dgs", "nimbus"):
        code, err = _run(main, [scene_dir, "--method", method, "--preset", "tiny", "--out", out, "--quiet",
                                "--set", item], capsys)
        assert code == 2 and "Traceback" not in err
        assert err.strip().splitlines() == [err.strip()] and err.startswith(f"error: --set {item}: must be ")
        assert not out.exists()


@pytest.mark.parametrize("item", ["haze.beta_range=[1]", "haze.beta=abc", "haze.fog_noise_octaves=0"])
def test_nimbus_synth_bad_set_exits_2_with_one_line_and_no_output(tmp_path, scene_dir, capsys, item):
    from weather_synth.cli import main

    out = tmp_path / "bench"
    code, err = _run(main, ["degrade", scene_dir, "--out", out, "--weather", "H", "--quiet", "--set", item], capsys)
    assert code == 2 and "Traceback" not in err
    assert err.strip().splitlines() == [err.strip()] and err.startswith(f"error: --set {item}: must be ")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == [] and Path(scene_dir).is_dir()


# --- sizes: a huge --set value is refused before the run, with its memory estimate (issue 35) ---------------------
@pytest.fixture
def no_runaway(monkeypatch):
    """Make the two places that ran for hours on a huge value fail at once instead, so a regression fails the
    test rather than hanging it: the march with millions of samples a ray, the dark channel's huge window."""
    import torch.nn.functional as F

    from nimbus.methods.nimbusgs import degradation

    march, max_pool2d = degradation.march, F.max_pool2d

    def guarded_march(*args, **kw):
        assert args[5] < 10**6, f"marched {args[5]} samples a ray"
        return march(*args, **kw)

    def guarded_pool(x, kernel_size, *args, **kw):
        sides = kernel_size if isinstance(kernel_size, tuple) else (kernel_size,)  # window_min: one axis a pass
        assert max(sides) < 10**6, f"a {kernel_size}-pixel minimum filter"
        return max_pool2d(x, kernel_size, *args, **kw)

    monkeypatch.setattr(degradation, "march", guarded_march)
    monkeypatch.setattr(F, "max_pool2d", guarded_pool)


@pytest.mark.parametrize("method, item, message", [
    ("nimbus-full", "ray_samples=2147483647", "GiB for one view's march at 64x48"),
    ("nimbus-full", "grid_resolution=100000", "GiB for the 100000^3 extinction grid"),
    ("nimbus-full", "airlight_hidden=2147483647", "GiB for the airlight network, 2147483647 wide, on one view at 64x48"),
    ("3dgs", "tile_size=2147483647", "GiB for the rasterizer's 2147483647x2147483647 tiles"),
    ("nimbus-full", "tile_size=100000", "GiB for the rasterizer's 100000x100000 tiles"),
])
def test_a_huge_size_is_refused_before_the_run_with_its_estimate(tmp_path, scene_dir, capsys, no_runaway, method,
                                                                  item, message):
    from nimbus.cli.train import main

    out = tmp_path / "run"
    short = ["--set", "iterations=4"] + (["--set", "m_init=2"] if method != "3dgs" else [])
    code, err = _run(main, [scene_dir, "--method", method, "--preset", "tiny", "--out", out, "--quiet", *short,
                            "--set", item], capsys)
    assert code == 2 and "Traceback" not in err, err
    assert err.strip().splitlines() == [err.strip()] and err.startswith(f"error: {item} ")
    assert message in err and "; the limit is " in err and "use at most " in err
    assert not out.exists()


def test_a_dark_channel_window_wider_than_the_image_is_the_whole_image(no_runaway):
    """dcp_patch=2**31 ran for hours (the minimum filter walks its padding); every window of at least twice the
    image gives the whole image's minimum, so the filter uses the smallest of them, with the same result."""
    import torch

    from nimbus.methods.nimbusgs.airlight import dark_channel_hard
    from nimbus.methods.nimbusgs.losses import soft_dark_channel

    image = torch.rand(6, 8, 3, generator=torch.Generator().manual_seed(0), requires_grad=True)
    whole = image.min().expand(6, 8)
    for patch in (15, 16, 1000, INT_MAX):
        assert torch.equal(dark_channel_hard(image, patch), whole)
        soft = soft_dark_channel(image, patch, 0.1)
        assert torch.equal(soft, soft_dark_channel(image, 15, 0.1)) and torch.allclose(soft, soft.min().expand(6, 8))
    (grad,) = torch.autograd.grad(soft_dark_channel(image, INT_MAX, 0.1).sum(), image)
    (expected,) = torch.autograd.grad(soft_dark_channel(image, 15, 0.1).sum(), image)
    assert torch.equal(grad, expected)


def test_the_size_limit_is_the_machines_or_nimbus_memory_limit_gib_and_the_advised_value_fits(scene_dir,
                                                                                                monkeypatch):
    """At 1 GiB, one 64x48 view's march fits 2**30 / (64 * 48 * MARCH_BYTES_PER_SAMPLE) samples a ray: one more
    is refused, that many builds."""
    from nimbus.data.io import load_scene
    from nimbus.methods.nimbusgs.scattering import MARCH_BYTES_PER_SAMPLE
    from nimbus.utils.memory import memory_limit

    scene = load_scene(scene_dir)
    nimbus = get_method("nimbus-full")
    fits = 2**30 // (64 * 48 * MARCH_BYTES_PER_SAMPLE)
    assert memory_limit()[1] in ("this machine's memory", "this container's memory limit")
    monkeypatch.setenv("NIMBUS_MEMORY_LIMIT_GIB", "1")
    assert memory_limit() == (2**30, "NIMBUS_MEMORY_LIMIT_GIB")
    base = apply_overrides(nimbus.preset("tiny"), {"iterations": "4", "m_init": "2"})
    with pytest.raises(NimbusError, match=rf"^ray_samples={fits + 1} needs about 1(\.0+)? GiB .*the limit is 1 GiB "
                                          rf"\(NIMBUS_MEMORY_LIMIT_GIB\); use at most {fits}$"):
        nimbus.load()(scene, dataclasses.replace(base, ray_samples=fits + 1))
    assert nimbus.load()(scene, dataclasses.replace(base, ray_samples=fits)).cfg.ray_samples == fits
    monkeypatch.setenv("NIMBUS_MEMORY_LIMIT_GIB", "lots")
    with pytest.raises(NimbusError, match="NIMBUS_MEMORY_LIMIT_GIB='lots' must be a positive number of GiB"):
        memory_limit()


def test_random_initial_points_are_sized_before_they_are_drawn():
    from conftest import make_tiny_scene
    from nimbus.methods.gs3d import GaussianSplatting

    scene = make_tiny_scene(n_points=0)
    with pytest.raises(NimbusError, match=r"^init_random_points=2147483647 needs about [\d,]+ GiB for 2147483647 "
                                          r"initial Gaussians"):
        GaussianSplatting(scene, dataclasses.replace(GS_PRESETS["tiny"], init_random_points=INT_MAX))
    assert GaussianSplatting(scene, dataclasses.replace(GS_PRESETS["tiny"], init_random_points=50)).num_gaussians == 50


# --- weather amounts beyond a physical bound (issue 35, item 7) ------------------------------------------------------
# rain.density_scale=1e12 asked for 1e12 streaks per pixel (the seeds alone ran out of memory), a length or size
# scale of 1e6 made a motion kernel or flake canvas the size of a city; rain.amount=1e6 clipped every streak to
# white without a word.  Each bound is where the rain or snow stops changing (see weather_synth/rain.py, snow.py).
@pytest.mark.parametrize("item, accepted", [
    ("rain.amount=1e6", "a number in [0, 10] (10: every streak peaks at white)"),
    ("rain.density_scale=1e12", "a number in [0, 1000]"),
    ("rain.length_scale=1e6", "a number in [0, 5]"),
    ("snow.amount=1e4", "a number in [0, 250]"),
    ("snow.size_scale=1e6", "a number in [0, 5]"),
])
def test_a_weather_amount_beyond_its_bound_is_refused_through_set(item, accepted):
    with pytest.raises(NimbusError) as e:
        apply_overrides(protocol_config(), parse_set_args([item]))
    assert str(e.value).startswith(f"--set {item}: must be ") and accepted in str(e.value)


def test_the_weather_bounds_admit_the_stability_storm_and_the_presets():
    from weather_synth.rain import MAX_RAIN_AMOUNT, rain_preset
    from weather_synth.snow import MAX_SNOW_AMOUNT, snow_preset

    cfg = apply_overrides(protocol_config(), parse_set_args(["rain.density_scale=100", "snow.amount=100",
                                                             f"rain.amount={MAX_RAIN_AMOUNT}"]))
    assert cfg.rain.density_scale == 100 and cfg.snow.amount == 100
    for name in ("light", "medium", "heavy"):
        SynthConfig(rain=rain_preset(name), snow=snow_preset(name))
    with pytest.raises(NimbusError, match=r"amount=250\.5: must be a number in \[0, 250\]"):
        SynthConfig(snow=snow_preset("heavy", amount=MAX_SNOW_AMOUNT + 0.5))


# --- Ctrl-C inside a compiled loop (issue 35, hole 5) ---------------------------------------------------------------
# `--set ray_samples=2147483647` is refused by the memory estimate above, but a sample count that fits can still
# march for minutes in one op, and torch.ops calls run without the GIL: Python only raised KeyboardInterrupt once
# the op returned.  The march now polls for Ctrl-C between blocks of rays (nimbus/kernels/csrc/interrupt.h).
MARCH_FOR_HOURS = textwrap.dedent("""
    import signal, sys, time, torch
    from nimbus.kernels.march import EXTENSION
    # Python's own Ctrl-C handler, whatever disposition the test process leaves to its children (an earlier test
    # in the same pytest process may have left SIGINT ignored, and an ignored SIGINT is inherited).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    assert EXTENSION.available()
    P, K = 10**5, 10**6  # 1e11 samples: hours of marching (K as large as a 64x48 view's memory check admits)
    f, o = torch.zeros(8, 8, 8), torch.tensor([-2.0, 0, 0])
    d, t0, t1 = torch.tensor([[1.0, 0, 0]]).repeat(P, 1), torch.zeros(P), torch.full((P,), 4.0)
    lo, hi = torch.full((3,), -1.0), torch.full((3,), 1.0)
    print("marching", flush=True)
    try:
        if sys.argv[1] == "forward":
            torch.ops.nimbus_march.march_forward(f, o, d, t0, t1, lo, hi, K)
        else:
            torch.ops.nimbus_march.march_backward(f, o, d, t0, t1, lo, hi, K, torch.ones(P))
        print("finished", flush=True)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
""")


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_ctrl_c_stops_a_march_that_would_run_for_hours(direction):
    from nimbus.kernels.march import EXTENSION

    if not EXTENSION.available(warn=False):
        pytest.skip("no compiled march kernel here (no compiler)")  # built here first: the child only loads it
    child = subprocess.Popen([sys.executable, "-c", MARCH_FOR_HOURS, direction], stdout=subprocess.PIPE, text=True,
                             env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        assert child.stdout.readline().strip() == "marching"
        time.sleep(0.5)  # inside the op by now (it starts in microseconds); an earlier signal is caught as well
        child.send_signal(signal.SIGINT)
        out, _ = child.communicate(timeout=120)  # a guard against a hang, not a timing assertion (hours without)
    finally:
        child.kill()
    assert out.strip() == "interrupted"


# Size-like synthesis settings the memory estimate does not cover: at 2**31 each ended in a traceback (a box filter's
# bad_alloc, a 16 GiB table or slice list) or ran for minutes (fog octaves).  Each has a bound where more stops
# mattering (weather_synth/haze.py, rain.py, snow.py), refused before anything is read or written.
@pytest.mark.parametrize("item, accepted", [
    ("haze.box_size=2147483647", "an integer in 1..4096"),
    ("haze.fog_table_samples=2147483647", "an integer in 1..4096"),
    ("haze.fog_noise_octaves=2147483647", "an integer in 1..16"),
    ("rain.slices=2147483647", "an integer in 1..64"),
    ("snow.slices=2147483647", "an integer in 1..64"),
])
def test_a_huge_synthesis_size_is_one_error_line_before_anything_is_written(tmp_path, scene_dir, capsys, item,
                                                                             accepted):
    from weather_synth.cli import main

    out = tmp_path / "bench"
    code, err = _run(main, ["degrade", scene_dir, "--out", out, "--weather", "H,R,S", "--quiet", "--protocol",
                            "physical", "--haze-mode", "heterogeneous", "--set", item], capsys)
    assert code == 2 and "Traceback" not in err and err.strip().splitlines() == [err.strip()], err
    assert err.startswith(f"error: --set {item}: must be {accepted}")
    assert list(tmp_path.iterdir()) == []
