"""nimbus.train.adam.Adam: torch.optim.Adam(fused=True)'s update without importing torch._dynamo."""

import subprocess
import sys

import pytest
import torch

from nimbus.train.adam import Adam


def _pair(seed=0):
    g = torch.Generator().manual_seed(seed)
    a = {"means": torch.randn(50, 3, generator=g), "sh": torch.randn(50, 4, 3, generator=g),
         "scalar": torch.randn((), generator=g)}
    return ({k: v.clone().requires_grad_(True) for k, v in a.items()},
            {k: v.clone().requires_grad_(True) for k, v in a.items()}, g)


def _groups(t, lrs):
    return [{"params": [t[k]], "lr": lrs[k], "name": k} for k in t]


def test_update_is_torchs_fused_adam_bit_for_bit():
    ours_t, ref_t, g = _pair()
    lrs = {"means": 1e-3, "sh": 2.5e-3, "scalar": 5e-2}
    ours = Adam(_groups(ours_t, lrs), lr=0.0, eps=1e-15)
    ref = torch.optim.Adam(_groups(ref_t, lrs), lr=0.0, eps=1e-15, fused=True)
    for it in range(7):
        for k in ours_t:
            grad = torch.randn(ours_t[k].shape, generator=g) * 10 ** -(it % 3)
            ours_t[k].grad, ref_t[k].grad = grad.clone(), grad.clone()
        if it == 3:  # a parameter without a gradient is left alone, as torch does
            ours_t["sh"].grad = ref_t["sh"].grad = None
        ours.step()
        ref.step()
        ours.zero_grad()
        ref.zero_grad()
        for k in ours_t:
            assert torch.equal(ours_t[k], ref_t[k]), k
    assert ours.state[ours_t["sh"]]["step"].item() == 6.0


def test_state_dict_round_trips_with_torch_optim_both_ways():
    ours_t, ref_t, g = _pair(1)
    lrs = {"means": 1e-2, "sh": 1e-3, "scalar": 1e-1}
    ours = Adam(_groups(ours_t, lrs), eps=1e-15)
    ref = torch.optim.Adam(_groups(ref_t, lrs), eps=1e-15, fused=True)
    for _ in range(3):
        for k in ours_t:
            grad = torch.randn(ours_t[k].shape, generator=g)
            ours_t[k].grad, ref_t[k].grad = grad.clone(), grad.clone()
        ours.step()
        ref.step()
    # a checkpoint written by torch.optim.Adam loads into ours, and ours into torch's
    ours2 = Adam(_groups({k: v.detach().clone().requires_grad_(True) for k, v in ref_t.items()}, lrs))
    ours2.load_state_dict(ref.state_dict())
    sd = ours.state_dict()
    assert sd["param_groups"][1]["name"] == "sh" and sd["param_groups"][1]["params"] == [1]
    ref2 = torch.optim.Adam(_groups({k: v.detach().clone().requires_grad_(True) for k, v in ours_t.items()}, lrs),
                            fused=True)
    ref2.load_state_dict(sd)
    for a, b in zip(ours2.state.values(), ref2.state.values()):
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(a[key], b[key])
    assert ours2.param_groups[0]["eps"] == 1e-15
    with pytest.raises(ValueError, match="other parameter groups"):
        Adam([{"params": [ours_t["means"]]}]).load_state_dict(sd)


def test_constructing_and_stepping_does_not_import_dynamo():
    code = ("import sys, torch\n"
            "from nimbus.train.params import GaussianParams\n"
            "p = GaussianParams({'means': torch.zeros(4, 3)}, {'means': 1e-3}, 1e-15)\n"
            "p['means'].grad = torch.ones(4, 3)\n"
            "p.optimizer.step()\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_refuses_what_it_cannot_optimise():
    leaf = torch.zeros(3, requires_grad=True)
    with pytest.raises(ValueError, match="more than one"):
        Adam([{"params": [leaf]}, {"params": [leaf]}])
    with pytest.raises(ValueError, match="leaf"):
        Adam([leaf * 2])
