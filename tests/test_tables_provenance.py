"""The provenance table: a store filled on several machines / commits says so, and inputs that differ are named."""

from __future__ import annotations

import csv
import io

from benchmark.cli import TOOL
from benchmark.store import ResultsStore, load_results
from benchmark.tables.comparison import tables as comparison_tables
from benchmark.tables.margins import tables as margins_tables
from benchmark.tables.provenance import machine, mixed_note, tables as provenance_tables
from benchmark.tables.writer import to_csv, to_markdown
from nimbus.cli_util import run_cli

AVX512 = {"nimbus": "0.1.0", "torch": "2.13.0+cpu", "cpu_isa": "avx512", "nimbus_commit": "aaaaaaaaaaaa"}
AVX2 = {"nimbus": "0.1.0", "torch": "2.13.0+cpu", "cpu_isa": "avx2", "nimbus_commit": "bbbbbbbbbbbb+modified"}


def record(scene, weather, method, psnr, versions, input_sha="1" * 64, device="cpu", day="2026-11-26"):
    return {"cell_id": f"{scene}-small_{weather}_{method}_fast_s0", "scene": scene, "size": "small",
            "weather": weather, "method": method, "preset": "fast", "seed": 0, "status": "ok", "psnr": psnr,
            "ssim": 0.5, "lpips": 0.2, "ssim_protocol": "3dgs", "lpips_net": "vgg", "train_time_s": 10.0,
            "device": device, "versions": versions, "input_sha256": input_sha, "finished_at": f"{day}T10:00:00Z"}


def store(tmp_path, recs):
    s = ResultsStore(tmp_path)
    for r in recs:
        s.append(r)
    return load_results(tmp_path)


def test_one_machine_one_input_has_one_row_and_no_warning(tmp_path):
    df = store(tmp_path, [record("garden", "H", "nimbus", 20.0, AVX512), record("garden", "H", "3dgs", 15.0, AVX512),
                          record("garden", "R", "nimbus", 25.0, AVX512, input_sha="2" * 64)])
    (table,), skipped = provenance_tables(df, ["nimbus"])
    assert skipped == []
    rows = table.blocks[0].rows
    assert [r.label for r in rows] == ["cpu (avx512), torch 2.13.0+cpu, code aaaaaaaaaaaa"]
    assert rows[0].values[("", "cells")] == "3"
    assert rows[0].values[("", "settings")] == "H, R" and rows[0].values[("", "methods")] == "nimbus, 3dgs"
    text = " ".join(table.notes)
    assert "one synthesised input" in text and "2 scene-settings" in text and "DIFFER" not in text
    assert mixed_note(df[df["status"] == "ok"]) is None
    for t in comparison_tables(df, ["nimbus"])[0] + margins_tables(df, ["nimbus"])[0]:
        assert not any(n.startswith("Provenance") for n in t.notes)


def test_mixed_machines_and_inputs_are_named_in_every_table(tmp_path):
    df = store(tmp_path, [
        record("garden", "H", "nimbus", 20.0, AVX512, day="2026-11-26"),
        record("garden", "H", "3dgs", 15.0, AVX2, input_sha="f" * 64, day="2026-11-28"),
        record("garden", "R", "nimbus", 25.0, AVX512, input_sha="2" * 64),
        {**record("garden", "R", "3dgs", 24.0, {"nimbus": "0.1.0"}, input_sha="2" * 64, device="cuda"),
         "rasterizer": "gsplat"},
    ])
    (table,), _ = provenance_tables(df, ["nimbus"])
    labels = [r.label for r in table.blocks[0].rows]
    assert labels == ["cpu (avx512), torch 2.13.0+cpu, code aaaaaaaaaaaa",
                      "cpu (avx2), torch 2.13.0+cpu, code bbbbbbbbbbbb+modified",
                      "cuda (not recorded), torch not recorded, code release 0.1.0"]
    assert table.blocks[0].rows[0].values[("", "finished")] == "2026-11-26"
    text = " ".join(table.notes)
    assert "several combinations" in text
    assert "Inputs DIFFER: garden H: 2 dataset manifests (111111111111, ffffffffffff)" in text
    assert "garden R" not in text.split("DIFFER")[1]  # R's two methods share one input
    by_weather = {t.layout: t for t in comparison_tables(df, ["nimbus"])[0]}
    h_note, r_note = by_weather["H"].notes[-1], by_weather["R"].notes[-1]
    assert h_note.startswith("Provenance:") and "2 device / CPU ISA / torch / code combinations" in h_note
    assert "garden H trained on different synthesised inputs" in h_note
    assert "different synthesised inputs" not in r_note and "2 device" in r_note
    # The device is named cell by cell where a table mixes devices (H's cells all ran on the CPU).
    assert "1 cell ran on cuda (the rest on cpu): 3dgs garden R" in r_note and "ran on" not in h_note
    (margins,), _ = margins_tables(df, ["nimbus"])
    assert "3 device" in margins.notes[-1] and "garden H" in margins.notes[-1]
    assert "1 cell ran on cuda (the rest on cpu): 3dgs garden R" in margins.notes[-1]
    lines = list(csv.DictReader(io.StringIO(to_csv([table]))))
    assert [(x["device"], x["cpu_isa"], x["code"], x["cells"]) for x in lines] == [
        ("cpu", "avx512", "aaaaaaaaaaaa", "2"), ("cpu", "avx2", "bbbbbbbbbbbb+modified", "1"),
        ("cuda", "not recorded", "release 0.1.0", "1")]
    assert [x["rasterizer"] for x in lines] == ["not recorded", "not recorded", "gsplat"]
    assert ("| cpu (avx2), torch 2.13.0+cpu, code bbbbbbbbbbbb+modified | 1 | H | 3dgs | not recorded | 2026-11-28 |"
            in to_markdown(table))


def test_an_old_record_without_versions_is_not_recorded_not_a_crash():
    assert machine({"status": "ok"}) == ("not recorded",) * 4
    assert machine({"status": "ok", "versions": "2.13"}) == ("not recorded",) * 4  # not a mapping: not a crash


def test_the_command_writes_the_provenance_files(tmp_path, capsys):
    root, out = tmp_path / "root", tmp_path / "out"
    root.mkdir()
    store(root, [record("garden", "H", "nimbus", 20.0, AVX512), record("garden", "H", "3dgs", 15.0, AVX2)])
    assert run_cli(TOOL.run, ["tables", "--root", str(root), "--out", str(out)]) == 0
    assert (out / "provenance.md").is_file() and (out / "provenance.tex").is_file()
    assert "### Where the figures were made" in (out / "comparisons.md").read_text()
    assert "Provenance:" in (out / "weather_H.md").read_text()
    assert "provenance.csv" in capsys.readouterr().out
