"""The training step's compiled kernels (nimbus/kernels/train_step.py) against the torch ops they replace."""

from __future__ import annotations

import math

import pytest
import torch

from nimbus.kernels import train_step
from nimbus.losses import l1, photometric_loss
from nimbus.metrics.image import SSIM_C1, SSIM_C2, loss_taps, mean_ssim

pytestmark = pytest.mark.skipif(not train_step.EXTENSION.available(warn=False),
                                reason="the training-step kernels cannot be built here")


def torch_loss(pred, gt, lam, mask=None):
    """The torch ops' loss (what photometric_loss computes when the kernel does not apply)."""
    return (1.0 - lam) * l1(pred, gt, mask) + lam * (1.0 - mean_ssim(pred, gt, mask))


def kernel_loss(pred, gt, lam, mask=None):
    return train_step.photometric_loss(pred, gt, lam, loss_taps(), SSIM_C1, SSIM_C2, mask)


def pair(h, w, c=3, seed=0, dtype=torch.float64):
    """A smooth-ish render and a noisy target in [0, 1], with a few exact ties (L1's kink)."""
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    base = torch.nn.functional.avg_pool2d(base.permute(2, 0, 1)[None], 3, 1, 1, count_include_pad=False)[0]
    pred = base.permute(1, 2, 0).contiguous()
    gt = (pred + 0.1 * torch.randn(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    gt[0, :2] = pred[0, :2]
    return pred.to(dtype), gt.to(dtype)


def value_and_grad(fn, pred, gt, lam, mask=None):
    p = pred.clone().requires_grad_(True)
    loss = fn(p, gt, lam, mask)
    loss.backward()
    return loss.detach(), p.grad


@pytest.mark.parametrize("shape", [(24, 31, 3), (5, 4, 3), (40, 13, 1), (17, 60, 2)])
@pytest.mark.parametrize("lam", [0.2, 0.4, 1.0])
def test_float64_value_and_gradient_equal_the_torch_loss(shape, lam):
    pred, gt = pair(*shape, seed=shape[0])
    ref_v, ref_g = value_and_grad(torch_loss, pred, gt, lam)
    v, g = value_and_grad(kernel_loss, pred, gt, lam)
    assert v.dtype == torch.float64 and v.shape == ()
    assert float(v) == pytest.approx(float(ref_v), rel=1e-12, abs=1e-15)
    torch.testing.assert_close(g, ref_g, rtol=1e-9, atol=1e-10 * float(ref_g.abs().max()))
    assert float(g.abs().max()) > 0


def test_masked_value_and_gradient_equal_the_torch_loss():
    pred, gt = pair(21, 26, seed=9)
    mask = torch.rand(21, 26, generator=torch.Generator().manual_seed(2)) > 0.3
    mask[3:9, 4:12] = False  # a hole wider than the window
    ref_v, ref_g = value_and_grad(torch_loss, pred, gt, 0.2, mask)
    v, g = value_and_grad(kernel_loss, pred, gt, 0.2, mask)
    assert float(v) == pytest.approx(float(ref_v), rel=1e-12)
    torch.testing.assert_close(g, ref_g, rtol=1e-9, atol=1e-10 * float(ref_g.abs().max()))
    assert torch.all(g[~mask] == 0)


def test_float32_stays_within_float_rounding_of_the_float64_loss():
    pred, gt = pair(48, 64, seed=3)
    ref_v, ref_g = value_and_grad(torch_loss, pred, gt, 0.2)
    v32, g32 = value_and_grad(kernel_loss, pred.float(), gt.float(), 0.2)
    t32, tg32 = value_and_grad(torch_loss, pred.float(), gt.float(), 0.2)
    assert v32.dtype == torch.float32 and g32.dtype == torch.float32
    # no further from the float64 truth than the torch float32 path is, give or take rounding
    assert abs(float(v32) - float(ref_v)) <= max(2 * abs(float(t32) - float(ref_v)), 1e-7)
    scale = float(ref_g.abs().max())
    err, torch_err = float((g32.double() - ref_g).abs().max()), float((tg32.double() - ref_g).abs().max())
    assert err <= max(2 * torch_err, 1e-5 * scale)


def test_gradcheck():
    pred, gt = pair(9, 13, seed=5)
    pred.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: kernel_loss(p, gt, 0.3), (pred,), eps=1e-6, atol=1e-8)


def test_bitwise_the_same_for_any_thread_count():
    pred, gt = pair(70, 90, seed=6, dtype=torch.float32)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        v1, g1 = value_and_grad(kernel_loss, pred, gt, 0.2)
        torch.set_num_threads(2)
        v2, g2 = value_and_grad(kernel_loss, pred, gt, 0.2)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(v1, v2) and torch.equal(g1, g2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(70, 90, 3), (5, 4, 3), (1, 7, 1), (40, 13, 2)])
@pytest.mark.parametrize("masked", [False, True])
def test_cached_target_moments_give_the_same_loss_and_gradient_bit_for_bit(dtype, shape, masked):
    pred, gt = pair(*shape[:2], c=shape[2], seed=8, dtype=dtype)
    mask = None
    if masked:
        mask = torch.ones(shape[:2], dtype=torch.bool)
        mask[:, 0] = False
    moments = train_step.target_moments(gt, loss_taps(), mask)
    assert moments.shape == (2, shape[2]) + shape[:2] and moments.dtype == dtype
    v0, g0 = value_and_grad(kernel_loss, pred, gt, 0.4, mask)
    cached = lambda p, g, lam, m: train_step.photometric_loss(p, g, lam, loss_taps(), SSIM_C1, SSIM_C2, m,  # noqa: E731
                                                              gt_moments=moments)
    v1, g1 = value_and_grad(cached, pred, gt, 0.4, mask)
    assert torch.equal(v0, v1) and torch.equal(g0, g1)
    # The first plane is the filtered target: at the centre of a constant 9x9 image, taps 1..9 of 11 each way.
    flat = torch.full((9, 9, 1), 0.5, dtype=dtype)
    m = train_step.target_moments(flat, loss_taps())
    assert float(m[0, 0, 4, 4]) == pytest.approx(0.5 * float(loss_taps()[1:10].sum()) ** 2, rel=1e-5)


def test_loss_target_moments_are_none_where_the_torch_loss_runs():
    from nimbus.losses import loss_target_moments

    pred, gt = pair(12, 10, seed=9, dtype=torch.float32)
    moments = loss_target_moments(gt)
    assert moments is not None
    p = pred.clone().requires_grad_(True)
    q = pred.clone().requires_grad_(True)
    a, b = photometric_loss(p, gt, 0.2), photometric_loss(q, gt, 0.2, gt_moments=moments)
    a.backward(), b.backward()
    assert torch.equal(a, b) and torch.equal(p.grad, q.grad)
    assert loss_target_moments(gt.to(torch.float16)) is None  # no kernel for half precision: nothing to keep
    wrong = train_step.target_moments(gt[:5], loss_taps())
    with pytest.raises(RuntimeError, match="gt_moments must be empty or target_moments"):
        photometric_loss(pred.clone().requires_grad_(True), gt, 0.2, gt_moments=wrong)


def test_photometric_loss_takes_the_kernel_only_where_it_applies(monkeypatch):
    pred, gt = pair(20, 24, seed=7)
    calls = []
    real = train_step.photometric_loss
    monkeypatch.setattr(train_step, "photometric_loss", lambda *a, **k: calls.append(1) or real(*a, **k))
    v = photometric_loss(pred.requires_grad_(True), gt, 0.2)
    assert calls and float(v) == pytest.approx(float(torch_loss(pred, gt, 0.2)), rel=1e-12)
    calls.clear()
    mask = torch.ones(20, 24, dtype=torch.bool)
    photometric_loss(pred, gt, 0.2, mask)                       # masks: the torch ops
    photometric_loss(pred[None], gt[None], 0.2)                 # batches
    photometric_loss(pred.detach(), gt.requires_grad_(True), 0.2)  # a target that wants a gradient
    assert not calls


def test_no_gradient_asked_gives_the_same_value():
    pred, gt = pair(16, 16, seed=8, dtype=torch.float32)
    with torch.no_grad():
        v = kernel_loss(pred, gt, 0.2)
    assert torch.equal(v, value_and_grad(kernel_loss, pred, gt, 0.2)[0])


def test_all_finite():
    x = torch.zeros(100_000)
    assert train_step.all_finite([x, torch.ones(3, dtype=torch.float64), torch.ones(4, dtype=torch.int64)])
    for bad in (math.nan, math.inf, -math.inf):
        y = x.clone()
        y[77_777] = bad
        assert not train_step.all_finite([torch.ones(2), y])
        assert not train_step.all_finite([y[1::2]])  # not contiguous: torch's isfinite
    assert train_step.all_finite([])
    assert train_step.all_finite([torch.ones(2, 3)[:, ::2], torch.ones(4, dtype=torch.int64)])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scale_rows_all_finite_is_torchs_broadcast_mul_bit_for_bit(dtype):
    gen = torch.Generator().manual_seed(0)
    n = 5000
    shapes = [(n,), (n, 3), (n, 15, 3), (n, 0)]
    grads = [torch.randn(s, generator=gen, dtype=dtype) * 1e3 for s in shapes]
    w = torch.rand(n, generator=gen, dtype=dtype) * 3
    expect = [g * w.reshape((n,) + (1,) * (g.dim() - 1)) for g in grads]
    threads = torch.get_num_threads()
    for count in (1, max(2, threads)):
        torch.set_num_threads(count)
        try:
            got = [g.clone() for g in grads]
            assert train_step.scale_rows_all_finite(got, w)
        finally:
            torch.set_num_threads(threads)
        assert all(torch.equal(a, b) for a, b in zip(got, expect))
    for bad_grad, bad_weight in ((math.inf, 1.0), (math.nan, 1.0), (1.0, math.inf), (3e38, 10.0)):
        got = [g.clone().float() for g in grads[:2]]
        got[1][4321, 2] = bad_grad
        ww = w.float().clone()
        ww[4321] = bad_weight
        assert not train_step.scale_rows_all_finite(got, ww)
    assert train_step.scale_rows_all_finite([], w)


def test_scale_rows_all_finite_takes_torch_where_the_kernel_does_not_apply():
    w = torch.tensor([1.0, 2.0, 0.5])
    f64 = torch.ones(3, 2, dtype=torch.float64)
    strided = torch.ones(3, 4)[:, ::2]
    assert train_step.scale_rows_all_finite([f64, strided], w)  # float64 rows, float32 weights; not contiguous
    assert torch.equal(f64, torch.tensor([[1.0, 1.0], [2.0, 2.0], [0.5, 0.5]], dtype=torch.float64))
    assert torch.equal(strided, torch.tensor([[1.0, 1.0], [2.0, 2.0], [0.5, 0.5]]))
    strided[1, 0] = math.nan
    assert not train_step.scale_rows_all_finite([strided], w)


def test_all_finite_of_no_cpu_float_tensor_loads_no_library(monkeypatch):
    # as for a CUDA run's gradients, which are never CPU tensors: the CPU library is not asked for (a CPU
    # library's build lock once stalled GPU workers)
    monkeypatch.setattr(train_step.EXTENSION, "available", lambda warn=True: pytest.fail("library asked for"))
    assert train_step.all_finite([torch.ones(3, dtype=torch.int64), torch.ones(2, 2)[:, ::2]])
    assert not train_step.all_finite([torch.tensor([[1.0, math.nan], [2.0, 3.0]]).t()])  # not contiguous


def test_gaussian_params_step_with_torchs_fused_adam_on_the_cpu():
    from nimbus.train.params import GaussianParams

    g = torch.Generator().manual_seed(0)
    tensors = {"means": torch.randn(40, 3, generator=g), "sh_rest": torch.randn(40, 15, 3, generator=g)}
    lrs = {"means": 1e-3, "sh_rest": 2e-4}
    params = GaussianParams(tensors, lrs, 1e-15)
    assert params.optimizer.defaults["fused"]
    ref = {k: v.clone().requires_grad_(True) for k, v in tensors.items()}
    ref_opt = torch.optim.Adam([{"params": [ref[k]], "lr": lrs[k]} for k in ref], lr=0.0, eps=1e-15)
    for _ in range(5):
        grads = {k: torch.randn(v.shape, generator=g) * 1e-2 for k, v in tensors.items()}
        for k in tensors:
            params[k].grad, ref[k].grad = grads[k].clone(), grads[k].clone()
        params.optimizer.step()
        ref_opt.step()
    for k in tensors:  # the same update up to float rounding
        torch.testing.assert_close(params[k], ref[k], rtol=1e-6, atol=1e-6)
    params.keep(torch.arange(40) % 3 > 0)  # densification surgery keeps working on its state
    params.optimizer.step()
