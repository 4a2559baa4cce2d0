"""nimbus.metrics PSNR / SSIM: protocols against closed forms, scikit-image and a direct (loop) implementation;
the torch path against training's former functions; the benchmark's score_images."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from benchmark.metrics import score_images
from nimbus.errors import NimbusError
from nimbus.metrics import (LPIPS, SSIM_PROTOCOLS, mean_ssim, peak_signal_noise_ratio, quantize_8bit,
                            random_state_dict, ssim_map, structural_similarity)

psnr = peak_signal_noise_ratio  # short names for the many calls below


def ssim(pred, gt, protocol="3dgs", **kwargs):
    return structural_similarity(pred, gt, protocol=protocol, **kwargs)


def smooth_pair(h: int, w: int, seed: int = 0, noise: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A blurred-noise texture (values over most of [0, 1]) and a noisy copy: float32 (H, W, 3)."""
    rng = np.random.default_rng(seed)
    gt = cv2.GaussianBlur(rng.random((h, w, 3), dtype=np.float32), (0, 0), 1.5)
    gt = (gt - gt.min()) / (gt.max() - gt.min())
    pred = np.clip(gt + rng.normal(0, noise, gt.shape), 0, 1).astype(np.float32)
    return pred, gt


# --- 8-bit round trip and PSNR --------------------------------------------------------------
def test_quantize_rounds_clips_and_zeroes_nan():
    x = np.array([0.0, 0.5 / 255, 1.49 / 255, 1.51 / 255, 1.2, -0.3, np.nan], np.float32)
    q = quantize_8bit(x) * 255
    np.testing.assert_allclose(q, [0, 1, 1, 2, 255, 0, 0], atol=1e-4)


def test_psnr_closed_form_and_batch():
    gt = np.full((20, 30, 3), 100 / 255, np.float32)
    preds = np.stack([gt + k / 255 for k in (1, 4, 16)])
    got = psnr(preds, np.broadcast_to(gt, preds.shape))
    np.testing.assert_allclose(got, [20 * math.log10(255 / k) for k in (1, 4, 16)], rtol=1e-6)
    assert got.shape == (3,)
    assert isinstance(psnr(preds[0], gt), float)


def test_psnr_quantizes_both_images():
    gt = np.full((16, 16, 3), 0.5, np.float32)
    # Differences below half an 8-bit step vanish in the round trip, so the images are equal.
    assert psnr(gt + 0.001, gt) == math.inf
    assert psnr(gt + 0.001, gt, quantize=False) == pytest.approx(60.0, abs=1e-3)


# --- SSIM ----------------------------------------------------------------------------------
def naive_ssim(a: np.ndarray, b: np.ndarray, padding: str, crop: int = 0, clamp: bool = False) -> float:
    """SSIM by explicit window sums per pixel (float64); the definition, written plainly."""
    half, sigma = 5, 1.5
    g = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    win = np.outer(g, g) / np.outer(g, g).sum()
    a, b = a.astype(np.float64), b.astype(np.float64)
    h, w, c = a.shape
    if padding == "same":
        a = np.pad(a, ((half, half), (half, half), (0, 0)))
        b = np.pad(b, ((half, half), (half, half), (0, 0)))
        rows, cols = range(h), range(w)
    else:
        rows, cols = range(h - 2 * half), range(w - 2 * half)
    c1, c2 = 0.01**2, 0.03**2
    out = np.zeros((len(rows), len(cols), c))
    for i in rows:
        for j in cols:
            pa = a[i:i + 2 * half + 1, j:j + 2 * half + 1]
            pb = b[i:i + 2 * half + 1, j:j + 2 * half + 1]
            for k in range(c):
                x, y = pa[..., k], pb[..., k]
                mx, my = (win * x).sum(), (win * y).sum()
                vx = (win * (x - mx) ** 2).sum()
                vy = (win * (y - my) ** 2).sum()
                cxy = (win * (x - mx) * (y - my)).sum()
                if clamp:
                    vx, vy = max(vx, np.finfo(np.float32).eps ** 2), max(vy, np.finfo(np.float32).eps ** 2)
                    cxy = np.sign(cxy) * min(np.sqrt(vx * vy), abs(cxy))
                out[i, j, k] = (2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    if crop:
        out = out[crop:-crop, crop:-crop]
    return float(out.mean())


@pytest.mark.parametrize("protocol,padding,crop,clamp", [
    ("3dgs", "same", 0, False), ("skimage", "same", 5, False), ("dmpix", "valid", 0, True),
])
def test_ssim_matches_direct_implementation(protocol, padding, crop, clamp):
    pred, gt = smooth_pair(17, 14, seed=1, noise=0.1)
    qp, qg = quantize_8bit(pred), quantize_8bit(gt)
    assert ssim(pred, gt, protocol) == pytest.approx(naive_ssim(qp, qg, padding, crop, clamp), abs=1e-12)


@pytest.mark.parametrize("shape", [(48, 64), (23, 37), (12, 530), (11, 11)])  # a wide strip; the smallest size
def test_ssim_skimage_protocol_matches_scikit_image(shape):
    from skimage.metrics import structural_similarity

    pred, gt = smooth_pair(*shape, seed=2)
    ref = structural_similarity(quantize_8bit(gt).astype(np.float64), quantize_8bit(pred).astype(np.float64),
                                data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False)
    assert ssim(pred, gt, "skimage") == pytest.approx(ref, abs=1e-12)


def test_3dgs_protocol_is_the_trainers_ssim_map_and_cropping_gives_skimage():
    pred, gt = smooth_pair(40, 52, seed=3)
    x, y = torch.from_numpy(quantize_8bit(pred)).double(), torch.from_numpy(quantize_8bit(gt)).double()
    m = ssim_map(x, y)  # the same SSIM the training loss optimises
    assert ssim(pred, gt, "3dgs") == pytest.approx(m.mean().item(), abs=1e-12)
    # The notes' observation: dropping a 5 px border of the 3dgs map gives skimage's value.
    assert ssim(pred, gt, "skimage") == pytest.approx(m[..., 5:-5, 5:-5].mean().item(), abs=1e-12)
    assert abs(ssim(pred, gt, "3dgs") - ssim(pred, gt, "skimage")) > 1e-3  # the protocols really differ
    # float32 (as the trainer runs) agrees to rounding level
    m32 = ssim_map(x.float(), y.float()).double().mean().item()
    assert ssim(pred, gt, "3dgs") == pytest.approx(m32, abs=2e-4)


@pytest.mark.parametrize("protocol", list(SSIM_PROTOCOLS))
def test_ssim_identity_symmetry_and_batch(protocol):
    pred, gt = smooth_pair(24, 20, seed=4)
    assert ssim(gt, gt, protocol) == pytest.approx(1.0, abs=1e-12)
    assert ssim(pred, gt, protocol) == pytest.approx(ssim(gt, pred, protocol), abs=1e-12)
    assert ssim(pred, gt, protocol) < 0.99
    batch = ssim(np.stack([pred, gt]), np.stack([gt, gt]), protocol)
    np.testing.assert_allclose(batch, [ssim(pred, gt, protocol), 1.0], atol=1e-12)


def test_ssim_bad_input_is_a_clear_error():
    pred, gt = smooth_pair(24, 20)
    with pytest.raises(NimbusError, match="unknown SSIM protocol 'ms-ssim'; use one of 3dgs, skimage, dmpix"):
        ssim(pred, gt, "ms-ssim")
    with pytest.raises(NimbusError, match="differ in shape"):
        ssim(pred[:10], gt)
    with pytest.raises(NimbusError, match="at least 11x11"):
        ssim(pred[:8, :8], gt[:8, :8])
    with pytest.raises(NimbusError, match=r"\(H, W, 3\)"):
        psnr(pred[..., 0], gt[..., 0])


# --- the torch path (training's evaluation) --------------------------------------------------
def _torch_pair(seed: int, h: int = 24, w: int = 32) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A float32 render and target (H, W, 3), with values outside [0, 1] and on 8-bit half steps, and a mask."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(h, w, 3, generator=g)
    pred = gt + 0.1 * torch.randn(h, w, 3, generator=g)
    pred[0, :8, 0] = (torch.arange(8) + 0.5) / 255  # exactly halfway between two 8-bit steps (or as near as float32 is)
    mask = torch.rand(h, w, generator=g) > 0.3
    return pred, gt, mask


def test_torch_quantize_rounds_and_clips():
    x = torch.tensor([0.0, 1.49 / 255, 1.51 / 255, 1.2, -0.3])
    np.testing.assert_allclose((quantize_8bit(x) * 255).numpy(), [0, 1, 2, 255, 0], atol=1e-4)
    assert quantize_8bit(x.double()).dtype == torch.float64


@pytest.mark.parametrize("masked", [False, True])
def test_torch_and_numpy_paths_agree(masked):
    pred, gt = smooth_pair(40, 52, seed=5)
    mask = np.zeros((40, 52), bool)
    mask[3:30, 5:47] = True
    m = mask if masked else None
    tm = torch.from_numpy(mask) if masked else None
    tp, tg = torch.from_numpy(pred), torch.from_numpy(gt)
    assert ssim(tp, tg, mask=tm) == pytest.approx(ssim(pred, gt, mask=m), abs=1e-5)
    assert psnr(tp, tg, mask=tm) == pytest.approx(psnr(pred, gt, mask=m), abs=1e-4)
    assert ssim(tp, tg, mask=tm) == float(mean_ssim(quantize_8bit(tp), quantize_8bit(tg), tm))


def test_torch_bad_input_is_a_clear_error():
    pred, gt, mask = _torch_pair(0)
    with pytest.raises(NimbusError, match="3dgs protocol only, not 'skimage'"):
        ssim(pred, gt, "skimage")
    with pytest.raises(NimbusError, match=r"must be \(H, W, 3\) RGB"):
        psnr(pred[None], gt[None])
    with pytest.raises(NimbusError, match="differ in shape"):
        psnr(pred[:10], gt)
    with pytest.raises(NimbusError, match="mask shape"):
        ssim(pred, gt, mask=mask[:10])
    # the zero-padded 3dgs map needs no full window (training evaluated small images so before)
    assert ssim(pred[:8, :8], gt[:8, :8]) < 1


# --- score_images ----------------------------------------------------------------------------
@pytest.fixture
def no_weights(tmp_path, monkeypatch):
    """An empty cache: the real LPIPS weights are 'not set up'."""
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "empty-cache"))


def test_score_images_values_means_and_mixed_sizes():
    pairs = [smooth_pair(32, 40, seed=s) for s in range(3)] + [smooth_pair(36, 44, seed=9)]
    preds, gts = [p for p, _ in pairs], [g for _, g in pairs]
    lp = LPIPS("alex", state_dict=random_state_dict("alex"))
    res = score_images(preds, gts, "dmpix", lp, names=["a", "b", "c", "d"])
    assert [r["name"] for r in res["per_view"]] == ["a", "b", "c", "d"]
    for r, p, g in zip(res["per_view"], preds, gts):
        assert r["psnr"] == pytest.approx(psnr(p, g))
        assert r["ssim"] == pytest.approx(ssim(p, g, "dmpix"))
        assert r["lpips"] == pytest.approx(lp(p, g), rel=1e-5) and r["lpips"] > 0
    for k in ("psnr", "ssim", "lpips"):
        assert res["mean"][k] == pytest.approx(np.mean([r[k] for r in res["per_view"]]))
    assert res["protocol"]["ssim"] == "dmpix" and res["protocol"]["lpips"] == "lpips-alex-v0.1"
    assert res["notes"] == [] and res["lpips_missing"] is None


def test_missing_lpips_weights_are_reported_never_zero(no_weights):
    pred, gt = smooth_pair(32, 32)
    with pytest.warns(UserWarning, match="nimbus-bench setup-weights"):
        res = score_images([pred], [gt], lpips_net="vgg")
    assert res["per_view"][0]["lpips"] is None and res["mean"]["lpips"] is None
    assert "nimbus-bench setup-weights" in res["lpips_missing"]
    assert res["setup_command"] == "nimbus-bench setup-weights"
    assert any("LPIPS not computed" in n for n in res["notes"])
    assert res["mean"]["psnr"] is not None  # the other metrics are still there


def test_score_images_notes_non_finite_predictions_and_identical_images():
    pred, gt = smooth_pair(24, 24)
    pred[0, 0, 0] = np.nan
    res = score_images([pred, gt], [gt, gt], lpips_net=None, names=["nan", "same"])
    assert res["per_view"][0]["psnr"] < 60 and res["per_view"][1]["psnr"] == math.inf
    assert any("NaN" in n and "nan (1 values)" in n for n in res["notes"])
    assert any("infinite" in n and "same" in n for n in res["notes"])
    assert res["protocol"]["lpips"] is None and res["per_view"][0]["lpips"] is None
