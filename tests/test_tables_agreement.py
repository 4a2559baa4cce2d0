"""`nimbus-bench compare`: two stores' shared cells, their differences, and whether the methods' order holds."""

from __future__ import annotations

import csv
import io

import pytest

from benchmark.cli import TOOL
from benchmark.store import ResultsStore, load_results
from benchmark.tables.agreement import compare
from benchmark.tables.writer import to_csv, to_markdown
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError

CPU = {"nimbus": "0.1.0", "torch": "2.13.0+cpu", "cpu_isa": "avx512", "nimbus_commit": "aaaaaaaaaaaa"}
GPU = {"nimbus": "0.1.0", "torch": "2.11.0", "cpu_isa": "avx2", "nimbus_commit": "aaaaaaaaaaaa"}


def record(weather, method, psnr, versions=CPU, device="cpu", ssim=0.5, lpips=0.2, seconds=100.0,
           input_sha="1" * 64, ssim_protocol="3dgs", net="vgg", seed=0):
    return {"cell_id": f"garden-small_{weather}_{method}_fast_s{seed}", "scene": "garden", "size": "small",
            "weather": weather, "method": method, "preset": "fast", "seed": seed, "status": "ok", "psnr": psnr,
            "ssim": ssim, "lpips": lpips, "ssim_protocol": ssim_protocol, "lpips_net": net, "train_time_s": seconds,
            "device": device, "versions": versions, "input_sha256": input_sha, "finished_at": "2026-11-26T10:00:00Z"}


def store(path, recs):
    path.mkdir(parents=True, exist_ok=True)
    s = ResultsStore(path)
    for r in recs:
        s.append(r)
    return load_results(path)


def gpu(weather, method, psnr, **kw):
    return record(weather, method, psnr, versions=GPU, device="cuda", **kw)


def test_differences_are_b_minus_a_and_a_swapped_pair_is_named(tmp_path):
    a = store(tmp_path / "a", [record("H", "nimbus", 20.0, ssim=0.70, lpips=0.20),
                               record("H", "3dgs", 15.0, seconds=200.0),
                               record("H", "robust-3dgs", 14.9),
                               record("R", "nimbus", 25.0), record("R", "3dgs", 22.0),
                               record("S", "nimbus", 26.0)])  # S: only in A
    b = store(tmp_path / "b", [gpu("H", "nimbus", 19.5, ssim=0.68, lpips=0.25),
                               gpu("H", "3dgs", 15.0, seconds=50.0),
                               gpu("H", "robust-3dgs", 15.2),  # overtakes 3dgs: an order that does not hold
                               gpu("R", "nimbus", 25.1), gpu("R", "3dgs", 21.9),
                               gpu("R+S", "3dgs", 18.0)])  # only in B
    table, lines = compare(a, b, names=("cpu", "cuda"), method_order=["nimbus"])
    assert [blk.name for blk in table.blocks] == ["garden H", "garden R"]
    h = {r.label: r.values for r in table.blocks[0].rows}
    assert list(h) == ["nimbus", "3dgs", "robust-3dgs"]
    assert h["nimbus"][("", "psnr_a")] == 20.0 and h["nimbus"][("", "psnr_b")] == 19.5
    assert h["nimbus"][("", "d_psnr")] == pytest.approx(-0.5)
    assert h["nimbus"][("", "d_ssim")] == pytest.approx(-0.02) and h["nimbus"][("", "d_lpips")] == pytest.approx(0.05)
    assert h["3dgs"][("", "time_ratio")] == pytest.approx(0.25)
    assert h["3dgs"][("", "input")] == "same"
    text = "\n".join(lines)
    assert "cpu: cpu (avx512), torch 2.13.0+cpu, code aaaaaaaaaaaa" in text
    assert "cuda: cuda (avx2), torch 2.11.0, code aaaaaaaaaaaa" in text
    assert "5 cells in both stores; only in cpu: 1, only in cuda: 1" in text
    assert "largest -0.50 (garden H nimbus)" in text
    assert "mean |ΔPSNR| 0.20" in text and "mean -0.04," in text  # (-0.5 + 0 + 0.3 + 0.1 - 0.1) / 5
    assert "the same in 1 of 2 scene-settings; garden H: 3dgs vs robust-3dgs (cpu: +0.10 dB, cuda: -0.20 dB)" in text
    assert "same synthesised bytes" in text
    md = to_markdown(table)
    assert "| Method | Scene, setting | PSNR cpu | PSNR cuda | ΔPSNR |" in md
    assert "| nimbus | garden H | 20.00 | 19.50 | -0.50 |" in md
    lines_csv = list(csv.DictReader(io.StringIO(to_csv([table]))))
    assert [(x["weather"], x["method"]) for x in lines_csv][:3] == [("H", "nimbus"), ("H", "3dgs"),
                                                                     ("H", "robust-3dgs")]
    assert float(lines_csv[0]["d_psnr"]) == pytest.approx(-0.5)


def test_inputs_made_again_with_other_bytes_are_flagged(tmp_path):
    a = store(tmp_path / "a", [record("H", "nimbus", 20.0), record("H", "3dgs", 15.0)])
    b = store(tmp_path / "b", [gpu("H", "nimbus", 20.0, input_sha="f" * 64), gpu("H", "3dgs", 15.0)])
    table, lines = compare(a, b)
    assert [r.values[("", "input")] for r in table.blocks[0].rows] == ["DIFFERS", "same"]
    assert any(line.startswith("Inputs DIFFER for 1 cells (garden H nimbus)") for line in lines)
    assert "the same in 1 of 1" in "\n".join(lines)  # equal figures: no swap
    assert "ΔPSNR (B - A): exactly 0 in all 2 cells" in lines


def test_methods_are_ordered_seed_by_seed(tmp_path):
    a = store(tmp_path / "a", [record("H", "nimbus", 20.0), record("H", "3dgs", 15.0),
                               record("H", "nimbus", 14.0, seed=1), record("H", "3dgs", 16.0, seed=1)])
    b = store(tmp_path / "b", [gpu("H", "nimbus", 20.0), gpu("H", "3dgs", 15.0),
                               gpu("H", "nimbus", 16.5, seed=1), gpu("H", "3dgs", 21.0, seed=1)])
    table, lines = compare(a, b)
    assert [r.label for r in table.blocks[0].rows] == ["nimbus", "nimbus (seed 1)", "3dgs", "3dgs (seed 1)"]
    # Within each seed the order holds; across seeds it would not (nimbus seed 0 against 3dgs seed 1: A +4.00,
    # B -1.00), and such a pair is no comparison of methods.
    assert "Method order by PSNR: the same in 1 of 1 scene-settings" in lines


def test_stores_that_cannot_be_compared_are_refused(tmp_path):
    a = store(tmp_path / "a", [record("H", "nimbus", 20.0)])
    with pytest.raises(NimbusError, match="share no finished cell"):
        compare(a, store(tmp_path / "b", [gpu("R", "nimbus", 20.0)]))
    with pytest.raises(NimbusError, match="score SSIM differently"):
        compare(a, store(tmp_path / "c", [gpu("H", "nimbus", 20.0, ssim_protocol="skimage")]))
    with pytest.raises(NimbusError, match="different networks"):
        compare(a, store(tmp_path / "d", [gpu("H", "nimbus", 20.0, net="alex")]))


def test_the_command_prints_the_summary_and_writes_three_files(tmp_path, capsys):
    store(tmp_path / "a", [record("H", "nimbus", 20.0), record("H", "3dgs", 15.0)])
    store(tmp_path / "b", [gpu("H", "nimbus", 20.3), gpu("H", "3dgs", 15.0)])
    before = (tmp_path / "a" / "results.jsonl").read_bytes()
    out = tmp_path / "out"
    argv = ["compare", "--root", str(tmp_path / "a"), "--against", str(tmp_path / "b"), "--names", "cpu,cuda"]
    assert run_cli(TOOL.run, argv + ["--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 cells in both stores" in printed and "largest +0.30 (garden H nimbus)" in printed
    assert sorted(p.name for p in out.iterdir()) == ["compare.csv", "compare.md", "compare.tex"]
    assert "PSNR cuda" in (out / "compare.md").read_text()
    assert (tmp_path / "a" / "results.jsonl").read_bytes() == before
    # Careless input: one line, non-zero exit, nothing written.
    assert run_cli(TOOL.run, ["compare", "--root", str(tmp_path / "a"), "--against", str(tmp_path / "a")]) != 0
    assert "same store" in capsys.readouterr().err
    assert run_cli(TOOL.run, ["compare", "--root", str(tmp_path / "a"), "--against", str(tmp_path / "nope"),
                              "--out", str(tmp_path / "out2")]) != 0
    assert "does not exist" in capsys.readouterr().err and not (tmp_path / "out2").exists()
    assert run_cli(TOOL.run, argv[:5] + ["--names", "cpu"]) != 0
    assert "two different names" in capsys.readouterr().err
