"""tools.gpu_check: what it says without CUDA, and its checks run on the CPU."""

from __future__ import annotations

import re

import pytest
import torch

from tools import gpu_check
from nimbus.train.run_folder import load_scene_arg


def test_without_cuda_it_says_so_and_exits_0(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu_check.main([]) == 0
    out = capsys.readouterr().out
    assert "no CUDA device here" in out and "PASS" not in out and "FAIL" not in out


def test_any_fail_makes_the_exit_status_1(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i: "fake GPU")
    verdicts = [gpu_check.Verdict("a", "PASS", "ok"), gpu_check.Verdict("b", "SKIP", "no gsplat")]
    monkeypatch.setattr(gpu_check, "run_checks", lambda *a: verdicts)
    assert gpu_check.main([]) == 0
    monkeypatch.setattr(gpu_check, "run_checks", lambda *a: verdicts + [gpu_check.Verdict("c", "FAIL", "off")])
    assert gpu_check.main([]) == 1
    assert "2 of 3 checks passed or skipped, 1 failed" in capsys.readouterr().out


def test_bad_arguments_are_one_line_and_exit_2_before_any_check(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i: "fake GPU")
    ran = []
    monkeypatch.setattr(gpu_check, "check_torch_vs_reference", lambda device: ran.append(device))
    assert gpu_check.main(["--scene", "builtin:nosuch"]) == 2
    captured = capsys.readouterr()
    assert not ran and "PASS" not in captured.out and "FAIL" not in captured.out
    assert captured.err.strip().splitlines() == [
        "gpu_check: unknown built-in scene 'nosuch'; choose one of: garden, street, tabletop "
        "(see `nimbus-synth scene --list`)"]
    with pytest.raises(SystemExit) as exc:
        gpu_check.main(["--iterations", "0"])
    assert exc.value.code == 2 and "'0' is not a whole number >= 1" in capsys.readouterr().err


def test_a_crashing_check_is_a_fail_line():
    def broken(device):
        raise RuntimeError("CUDA error: no kernel image is available\nmore")

    (v,) = gpu_check._guarded(broken, "torch vs reference", "cuda")
    assert v.status == "FAIL"
    assert v.line() == "FAIL  torch vs reference: RuntimeError: CUDA error: no kernel image is available"


def test_traceback_flag_prints_the_crash_to_stderr(monkeypatch, capsys):
    def broken(device):
        raise RuntimeError("deep inside")

    gpu_check._guarded(broken, "march", "cuda")
    assert "Traceback" not in capsys.readouterr().err
    monkeypatch.setattr(gpu_check, "_TRACEBACKS", True)
    (v,) = gpu_check._guarded(broken, "march", "cuda")
    err = capsys.readouterr().err
    assert v.status == "FAIL" and "Traceback" in err and "in broken" in err and "deep inside" in err


def test_torch_backend_and_march_checks_pass_on_the_cpu():
    v = gpu_check.check_torch_vs_reference("cpu")
    assert v.status == "PASS", v.line()
    v = gpu_check.check_march("cpu")
    assert v.status == "PASS", v.line()


def test_gsplat_is_skipped_off_cuda():
    verdicts = gpu_check.check_gsplat("cpu")
    assert [v.status for v in verdicts] == ["SKIP", "SKIP"]
    assert "CUDA-only" in verdicts[0].detail


@pytest.mark.parametrize("method", ["3dgs", "nimbus-full"])
def test_training_check_compares_psnr_within_the_tolerance(method):
    scene = load_scene_arg("builtin:garden:tiny")
    psnr, seconds, peak_mb = gpu_check.train_psnr(method, scene, "cpu", 12)
    assert 5.0 < psnr < 60.0 and seconds > 0 and peak_mb > 50  # a torch process's resident set, at the least
    same = gpu_check.check_training(method, scene, "cpu", 12, cpu_psnr=psnr)
    assert same.status == "PASS" and "+0.00 dB" in same.detail, same.line()  # CPU training is deterministic
    assert re.search(r"peak memory \d+ MB$", same.detail), same.line()
    off = gpu_check.check_training(method, scene, "cpu", 12, cpu_psnr=psnr + 2 * gpu_check.PSNR_TOLERANCE_DB)
    assert off.status == "FAIL", off.line()
