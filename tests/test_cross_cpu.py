"""Same results on any x86-64 CPU: synthesis under emulated CPUs, and the compositing kernel's clones.

Another CPU is emulated on this one with the libraries' own dispatch switches
(:data:`benchmark.reference.EMULATED_CPUS`: numpy, OpenCV, torch, OpenBLAS and glibc take
their AVX2-only or pre-AVX code paths), set in a child process before the libraries load.
On a machine with AVX-512 this is where numpy's SVML ``arctan2`` (7 % of float64 results one
ulp off its AVX2 path) changed the recorded fall angles and so every R+S manifest; on a
machine without AVX-512 the "avx2" child takes the native paths and the comparison is weaker.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmark.reference import EMULATED_CPUS
from nimbus.data.camera import Camera
from nimbus.data.images import read_image
from nimbus.errors import NimbusError
from weather_synth.particles import fall_direction, image_fall_angle, motion_kernel, slice_depths

REPO = Path(__file__).resolve().parents[1]


def run_child(code: str, cpu: str | None, **env) -> subprocess.CompletedProcess:
    """``python -c code`` from the repository root, as on the emulated ``cpu`` (None: this CPU)."""
    full_env = {k: v for k, v in os.environ.items() if k != "NIMBUS_CPU_ISA"}
    full_env.update({"PYTHONPATH": str(REPO), **(EMULATED_CPUS[cpu] if cpu else {}), **env})
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=full_env, capture_output=True, text=True,
                          timeout=120)


def geometry_values() -> dict:
    """What places particles, for many random cameras and winds: the geometry as exact hex floats, and the
    streak kernels (shape and largest value)."""
    rng = np.random.default_rng(5)
    exact, kernels = [], []
    for i in range(150):
        up = rng.normal(size=3)
        d = fall_direction(up, rng.uniform(0, 30), rng.uniform(0, 360))
        eye = rng.normal(size=3) * 5
        cam = Camera.look_at(eye, rng.normal(size=3), (0, 0, 1), 96, 72, 40 + 30 * rng.random())
        angle = image_fall_angle(cam, d)
        depths = slice_depths(np.random.default_rng(i), (0.1, 2.5), 3, rng.uniform(0.5, 20))
        kern = motion_kernel(rng.uniform(1, 30), angle, rng.uniform(0, 2))
        exact += [float(x).hex() for x in (*d, angle, *depths)] + [str(kern.shape)]
        kernels.append(float(kern.max()))
    return {"exact": exact, "kernels": kernels}


@pytest.mark.parametrize("cpu", sorted(EMULATED_CPUS))
def test_particle_geometry_does_not_depend_on_the_cpus_maths_paths(cpu):
    child = run_child("import json; from tests.test_cross_cpu import geometry_values; "
                      "print(json.dumps(geometry_values()))", cpu)
    assert child.returncode == 0, child.stderr[-2000:]
    here, there = geometry_values(), json.loads(child.stdout.splitlines()[-1])
    differ = [i for i, (a, b) in enumerate(zip(here["exact"], there["exact"])) if a != b]
    assert len(here["exact"]) == len(there["exact"]) and not differ, (
        f"{len(differ)} values differ, first {differ[:5]}")
    # OpenCV's float Gaussian blur rounds differently on pre-AVX2 paths: the kernels agree to float32 rounding.
    np.testing.assert_allclose(here["kernels"], there["kernels"], rtol=1e-6)


SYNTH = """
import sys
from tests.conftest import make_tiny_scene
from weather_synth.config import protocol_config
from weather_synth.dataset import degrade_scene
from weather_synth.settings import parse_setting
for protocol in ("onerestore", "physical"):
    degrade_scene(make_tiny_scene(n_views=3, depth=True), sys.argv[1] + "/" + protocol,
                  [parse_setting("H+R+S")], protocol_config(protocol, 0), progress=False)
"""


def without_hashes(x):
    """A manifest with its byte hashes removed (what is left records every synthesis decision)."""
    if isinstance(x, dict):
        return {k: without_hashes(v) for k, v in x.items() if not k.endswith("sha256")}
    if isinstance(x, list):
        return [without_hashes(v) for v in x]
    return x


@pytest.mark.slow
def test_synthesis_gives_the_same_data_on_each_emulated_cpu(tmp_path):
    outs = {}
    for cpu in (None, *sorted(EMULATED_CPUS)):
        out = tmp_path / (cpu or "native")
        child = subprocess.run([sys.executable, "-c", SYNTH, str(out)], cwd=REPO, capture_output=True, text=True,
                               env={**os.environ, "PYTHONPATH": str(REPO), **(EMULATED_CPUS[cpu] if cpu else {})},
                               timeout=120)
        assert child.returncode == 0, child.stderr[-2000:]
        outs[cpu or "native"] = out
    for protocol in ("onerestore", "physical"):
        base = outs["native"] / protocol / "H+R+S"
        manifest = json.loads((base / "manifest.json").read_text())
        for cpu in EMULATED_CPUS:
            other = outs[cpu] / protocol / "H+R+S"
            assert without_hashes(json.loads((other / "manifest.json").read_text())) == without_hashes(manifest), (
                f"{protocol} on {cpu}: the recorded synthesis differs")
            for view in manifest["views"]:
                a, b = read_image(base / view["image"]), read_image(other / view["image"])
                assert np.abs(a - b).max() <= 1 / 255 + 1e-6, f"{protocol} {cpu} {view['name']}"
                la, lb = np.load(base / view["layers"]), np.load(other / view["layers"])
                for name in la.files:
                    np.testing.assert_allclose(la[name], lb[name], atol=1 / 255, rtol=0, equal_nan=True,
                                               err_msg=f"{protocol} {cpu} {view['name']} {name}")


def test_nimbus_cpu_isa_is_applied_when_the_kernel_loads_and_a_bad_value_is_an_error():
    from nimbus.kernels import raster

    if not raster.available(warn=False):
        pytest.skip(f"no compiled kernel here ({raster.load_error()})")
    code = ("from nimbus.errors import NimbusError\n"
            "from nimbus.kernels import raster\nfrom nimbus.render import backends\n"
            "try:\n"
            "    print(backends.available('cpp'), raster.cpu_isa())\n"
            "except NimbusError as e:\n"
            "    print('error:', e)\n")
    child = run_child(code, None, NIMBUS_CPU_ISA="generic")
    assert child.stdout.split() == ["True", "generic"], child.stderr[-2000:]
    child = run_child(code, None, NIMBUS_CPU_ISA="avx9")
    assert child.stdout.startswith("error: NIMBUS_CPU_ISA=avx9 is not an instruction set"), child.stderr[-2000:]
    child = run_child(code, None, NIMBUS_CPU_ISA="")  # empty: the best clone, as unset
    assert child.stdout.split() == ["True", raster.cpu_isas()[-1]], child.stderr[-2000:]


def test_a_clone_the_cpu_cannot_run_is_refused(monkeypatch):
    from nimbus.kernels import raster

    if not raster.available(warn=False):
        pytest.skip(f"no compiled kernel here ({raster.load_error()})")
    before = raster.cpu_isa()
    monkeypatch.setattr(raster, "cpu_isas", lambda: ("generic",))
    with pytest.raises(NimbusError, match="cannot run the avx512 clone; it runs generic"):
        raster.set_cpu_isa("avx512")
    monkeypatch.setenv("NIMBUS_CPU_ISA", "avx2")
    with pytest.raises(NimbusError, match="NIMBUS_CPU_ISA=avx2"):
        raster.available()
    monkeypatch.undo()
    assert raster.available() and raster.cpu_isa() == before
