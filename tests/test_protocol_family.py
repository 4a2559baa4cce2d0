"""The physical synthesis protocol as a setting family of its own: tokens, data, store keys, tables.

``--weathers H@physical`` runs haze synthesised with one medium per scene; the default
settings keep the OneRestore protocol (beta and airlight drawn per view).  End to end on a
tiny grid: synthesis into its own data folder, cells keyed apart, a table of its own.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmark.cell import CellOptions, data_dir
from benchmark.cli import TOOL
from benchmark.grid import InlineExecutor, build_cells, resolve_methods, run_grid
from benchmark.store import load_results
from benchmark.tables.comparison import tables as comparison_tables
from benchmark.tables.summary import summary_text
from nimbus.cli_util import run_cli
from nimbus.data.images import read_image
from nimbus.errors import NimbusError
from weather_synth.settings import family_order, parse_family_setting, parse_family_weather, parse_weather


def test_family_tokens():
    names = [s.name for s in parse_family_weather("H, r@physical, haze+rain@PHYSICAL, H@onerestore, all@physical")]
    assert names[:3] == ["H", "R@physical", "H+R@physical"]  # H@onerestore is H: dropped as a duplicate
    assert names[3:] == ["H@physical", "S@physical", "H+S@physical", "R+S@physical", "H+R+S@physical"]
    # Without '@' the grammar is parse_weather's, names and order included.
    assert [s.name for s in parse_family_weather("all")] == [s.name for s in parse_weather("all")]
    f = parse_family_setting("h+s@physical")
    assert (f.setting.name, f.protocol, f.description) == ("H+S", "physical", "haze + snow, physical protocol")
    assert family_order()[:7] == ("H", "R", "S", "H+R", "H+S", "R+S", "H+R+S")
    assert family_order()[7] == "H@physical" and len(family_order()) == 14
    for bad, msg in (("H@fog", "unknown protocol 'fog'"), ("@physical", "empty weather setting"),
                     ("H@", "unknown protocol ''"), ("X@physical", "unknown weather token")):
        with pytest.raises(NimbusError, match=msg):
            parse_family_weather(bad)


def test_cells_and_data_of_a_family(tmp_path):
    plain, physical = build_cells(["garden"], ["h", "H@Physical"], ["3dgs"], ["tiny"], [0])
    assert plain.cell_id == "garden-tiny_H_3dgs_tiny_s0"  # the default family's ids are unchanged
    assert physical.cell_id == "garden-tiny_H@physical_3dgs_tiny_s0"
    assert data_dir(tmp_path, plain) == tmp_path / "data" / "garden-tiny" / "H"
    assert data_dir(tmp_path, physical) == tmp_path / "data" / "garden-tiny@physical" / "H"


def test_default_methods_include_the_restore_baseline():
    assert resolve_methods(None) == (["nimbus", "3dgs", "restore-3dgs"], [])


def test_physical_family_end_to_end(tmp_path, capsys):
    """synthesis -> two tiny cells (H in each family) -> store -> tables with a physical table of its own."""
    root = tmp_path / "bench"
    cells = build_cells(["garden"], ["H", "H@physical"], ["3dgs"], ["tiny"], [0], "tiny", {"iterations": "5"})
    outcome = run_grid(cells, root, InlineExecutor(), CellOptions(lpips_net=None), progress=False,
                       log=lambda s: None)
    assert [r["status"] for r in outcome.ran] == ["ok", "ok"], [r.get("error") for r in outcome.ran]
    plain, physical = (data_dir(root, c) for c in cells)
    assert json.loads((plain / "manifest.json").read_text())["protocol"] == "onerestore"
    assert json.loads((physical / "manifest.json").read_text())["protocol"] == "physical"
    name = sorted(p.name for p in (plain / "images").iterdir())[0]
    assert not np.array_equal(read_image(plain / "images" / name), read_image(physical / "images" / name))
    df = load_results(root)
    assert sorted(df["cell_id"]) == sorted(c.cell_id for c in cells)
    assert cells[1].cell_id.startswith("garden-tiny_H@physical_3dgs_tiny_s0")
    assert sorted(df["weather"]) == ["H", "H@physical"]
    tables = {t.key: t for t in comparison_tables(df, ["3dgs"])[0]}
    assert list(tables) == ["weather_H", "weather_H_physical"]
    h, hp = tables["weather_H"], tables["weather_H_physical"]
    assert h.title == "haze (H)" and hp.title.startswith("haze (H), physical protocol: one medium per scene")
    assert "Synthesis protocol: onerestore (the paper's data: haze beta and airlight drawn per view" in h.notes[0]
    assert "Synthesis protocol: physical (one medium per scene" in hp.notes[0]
    assert hp.layout == "H@physical" and hp.label == "tab:nimbus-bench-H-physical"
    assert h.row("3dgs").values[("garden", "psnr")] != hp.row("3dgs").values[("garden", "psnr")]
    summary = summary_text(df, ["3dgs"]).splitlines()
    assert [line.split()[0] for line in summary[1:3]] == ["H", "H@physical"]
    out = tmp_path / "tables"
    assert run_cli(TOOL.run, ["tables", "--root", str(root), "--out", str(out)]) == 0
    assert "weather_H_physical.md" in capsys.readouterr().out
    md = (out / "weather_H_physical.md").read_text()
    assert "physical protocol" in md and "paper's reported numbers" not in md  # the paper's H is another protocol
    rows = (out / "comparisons.csv").read_text().splitlines()
    assert rows[0].split(",")[:3] == ["weather", "protocol", "method"]
    assert any(r.startswith("H@physical,physical,3dgs,") for r in rows)


def test_synth_help_names_what_each_protocol_draws(capsys):
    from weather_synth.cli import main

    for argv in (["--help"], ["degrade", "--help"]):
        with pytest.raises(SystemExit):
            main(argv)
        text = " ".join(capsys.readouterr().out.split())
        assert "onerestore" in text and "beta and airlight drawn per view" in text, argv
        assert "physical: one medium per scene" in text, argv
