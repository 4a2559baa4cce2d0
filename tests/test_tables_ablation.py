"""Ablation and complexity / runtime tables from a synthetic results store: values, marks, missing rows,
LaTeX / Markdown structure, the paper's numbers beside ours, and the ``nimbus-bench tables`` listing."""

from __future__ import annotations

import csv
import io
import re

import pytest

from benchmark.cli import TOOL
from benchmark.data import PAPER_ABLATIONS_DIR as ABLATION_REFERENCE_DIR
from benchmark.store import ResultsStore, load_results
from benchmark.tables import ablation, runtime
from benchmark.tables.ablation import ABLATIONS, OURS
from benchmark.tables.model import rank_marks
from benchmark.tables.results import ABLATION_OURS, COMPARISON_OURS, METRIC_COLUMNS, METRICS
from benchmark.tables.runtime import COLUMNS as RUNTIME_COLUMNS
from benchmark.tables.writer import to_csv, to_latex, to_markdown
from nimbus.cli_util import run_cli

# (method, weather, scene, psnr, ssim, lpips).  Components: on H, nimbus-full is best everywhere and
# uniform extinction second; on H+R+S, w/o GGS is run on garden only (no Average).  GGS factors: w/o Depth on
# both scenes.  M_init: 1K and 4K on both scenes.  Nothing for the loss ablation or the rainy block.
ROWS = [
    ("nimbus-full", "H", "garden", 21.0, 0.70, 0.20), ("nimbus-full", "H", "street", 23.0, 0.80, 0.10),
    ("nimbus-uniform-extinction", "H", "garden", 20.0, 0.60, 0.25),
    ("nimbus-uniform-extinction", "H", "street", 22.0, 0.70, 0.15),
    ("nimbus-gaussian-extinction", "H", "garden", 18.0, 0.50, 0.40),
    ("nimbus-gaussian-extinction", "H", "street", 19.0, 0.55, 0.35),
    ("nimbus-full", "H+R+S", "garden", 20.0, 0.60, 0.30), ("nimbus-full", "H+R+S", "street", 22.0, 0.70, 0.20),
    ("nimbus-no-ggs", "H+R+S", "garden", 19.0, 0.65, 0.35),
    ("nimbus-ggs-no-depth", "H+R+S", "garden", 19.5, 0.55, 0.32),
    ("nimbus-ggs-no-depth", "H+R+S", "street", 21.5, 0.65, 0.22),
    ("nimbus-minit-1k", "H+R+S", "garden", 17.0, 0.50, 0.40), ("nimbus-minit-1k", "H+R+S", "street", 18.0, 0.60, 0.3),
    ("nimbus-minit-4k", "H+R+S", "garden", 20.0, 0.60, 0.30), ("nimbus-minit-4k", "H+R+S", "street", 22.0, 0.7, 0.2),
    ("3dgs", "H+R+S", "garden", 15.0, 0.40, 0.50), ("3dgs", "H+R+S", "street", 16.0, 0.45, 0.45),
]


def records(preset="tiny", device="cpu"):
    out = []
    for i, (method, weather, scene, p, s, lp) in enumerate(ROWS):
        out.append({"cell_id": f"{scene}-tiny_{weather}_{method}_{preset}_s0", "scene": scene, "size": "tiny",
                    "weather": weather, "method": method, "preset": preset, "seed": 0, "status": "ok",
                    "psnr": p, "ssim": s, "lpips": lp, "ssim_protocol": "3dgs", "lpips_net": "vgg",
                    "train_time_s": 60.0 * (2 if method == "3dgs" else 3), "peak_memory_mb": 512.0 + i,
                    "num_params": 250_000, "render_fps": 40.0, "device": device})
    return out


#: The label of the ablation tables' "Ours" row (the ``nimbus-full`` method).
OURS_LABEL = ABLATION_OURS.label
HIGHER_IS_BETTER = {c.key: c.higher_is_better for c in METRIC_COLUMNS}
DECIMALS = {c.key: c.decimals for c in METRIC_COLUMNS}


def ablation_tables(df, method_order=()):
    """Our ablation tables, then the runtime table(s), and the layouts skipped (as ``nimbus-bench tables`` lists)."""
    ours, skipped = ablation.tables(df, method_order)
    times, missing = runtime.tables(df, method_order)
    return ours + times, skipped + missing


def paper_ablation_tables():
    return {**ablation.paper(), **runtime.paper()}


def _store(root, recs):
    store = ResultsStore(root)
    for r in recs:
        store.append(r)
    return load_results(root)


@pytest.fixture
def built(tmp_path):
    tables, skipped = ablation_tables(_store(tmp_path, records()), ["nimbus-full", "3dgs"])
    return {t.key: t for t in tables}, skipped


def test_ablation_rows_are_registered_methods():
    from nimbus.methods.registry import METHODS

    for spec in ABLATIONS:
        assert set(spec.methods) <= set(METHODS), spec.key
        labels = [r.label for b in spec.blocks for r in b.rows]
        for b in spec.blocks:
            assert len({r.label for r in b.rows}) == len(b.rows)  # labels identify rows within a block
        assert labels


def test_ours_row_is_the_base_every_variant_changes_one_thing_of(built):
    """The ablation "Ours" row is nimbus-full and says so; each variant row's method is that same
    method's config with exactly the field(s) it ablates changed, so the row's difference to "Ours"
    is that one change."""
    import dataclasses

    from nimbus.methods.registry import get_method

    assert OURS == ABLATION_OURS.method == "nimbus-full" and OURS_LABEL == "Ours (nimbus-full: csm+plm+ggs)"
    base = dataclasses.asdict(get_method(OURS).preset("tiny"))
    for spec in ABLATIONS:
        for b in spec.blocks:
            assert [r.method for r in b.rows].count(OURS) <= 1
            for r in b.rows:
                if r.method == OURS:
                    continue
                changed = {k for k, v in dataclasses.asdict(get_method(r.method).preset("tiny")).items()
                           if base[k] != v}
                if spec.key == "ablation_minit":  # the schedule's own M_init (4k) is the base itself
                    assert changed <= {"m_init"}, (r.method, changed)
                else:
                    assert len(changed) == 1, (r.method, changed)
    t = built[0]["ablation_components"]
    note = " ".join(t.notes)
    assert "Ours = nimbus-full (csm+plm+ggs)" in note and f"Ours is {COMPARISON_OURS.method}" in note
    assert all(t.row(OURS_LABEL, i).fields["method"] == OURS for i in range(3))
    assert "| Ours (nimbus-full: csm+plm+ggs) |" in to_markdown(t)


def test_tables_built_and_skipped(built):
    tables, skipped = built
    assert list(tables) == ["ablation_components", "ablation_ggs", "ablation_minit", "runtime"]
    assert skipped == ["ablation_loss (tab:ablation_loss)"]


def test_component_values_marks_and_missing(built):
    t = built[0]["ablation_components"]
    assert [b.fields["weather"] for b in t.blocks] == ["H", "R", "H+R+S"] and t.groups == ["Average"]
    hazy = [r.label for r in t.blocks[0].rows]
    assert hazy == ["Gaussian-Driven Extinction", "Uniform Extinction", "w/o CSM", OURS_LABEL]
    assert t.row(OURS_LABEL, 0).values[("Average", "psnr")] == pytest.approx(22.0)
    assert t.row("Uniform Extinction", 0).values[("Average", "ssim")] == pytest.approx(0.65)
    assert t.row("w/o CSM", 0).values.get(("Average", "psnr")) is None  # not run: missing, never zero
    assert t.marks("Average", "psnr", 0) == [None, 2, None, 1]
    assert t.marks("Average", "lpips", 0) == [None, 2, None, 1]
    assert all(r.values.get(("Average", k)) is None for r in t.blocks[1].rows for k in METRICS)
    # w/o GGS ran on garden only: no Average, and the note says why
    no_ggs = t.row("w/o GGS", 2)
    assert no_ggs.values[("Average", "psnr")] is None and no_ggs.values[("garden", "psnr")] == 19.0
    assert t.marks("Average", "psnr", 2) == [None, None]  # one value: nothing to rank
    assert any("w/o GGS (nimbus-no-ggs) was run on 1 of the 2 H+R+S scenes" in n for n in t.notes)
    assert any("rows not in the paper's table: w/o CSM, w/o PLM" in n for n in t.notes)


def test_minit_has_scene_groups(built):
    t = built[0]["ablation_minit"]
    assert t.groups == ["garden", "street"] and [r.label for r in t.blocks[0].rows] == ["1K", "2K", "4K", "10K", "15K"]
    assert t.marks("street", "psnr", 0) == [None, None, 1, None, None]  # two values: best only
    assert t.row("2K", 0).values.get(("garden", "psnr")) is None


def _latex_parts(tex: str) -> tuple[int, list[str], list[str]]:
    spec = re.search(r"\\begin\{tabular\}\{([^}]*)\}", tex).group(1)
    head = tex.split(r"\toprule", 1)[1].split(r"\midrule", 1)[0]
    body = tex.split(r"\midrule", 1)[1].split(r"\bottomrule", 1)[0]
    rows = [re.sub(r"^\s*(\\midrule|\\cmidrule\(lr\)\{\d+-\d+\})\s*", "", r) for r in body.split(r"\\")]
    heads = [h for h in head.split(r"\\") if "&" in h]
    return len(spec.replace(" ", "")), heads, [r for r in rows if r.strip()]


@pytest.mark.parametrize("key", ["ablation_components", "ablation_ggs", "ablation_minit", "runtime"])
def test_latex_and_markdown_structure(built, key):
    t = built[0][key]
    tex = to_latex(t)
    assert tex.count("{") == tex.count("}")
    for env in ("table", "tabular"):
        assert tex.count(rf"\begin{{{env}}}") == tex.count(rf"\end{{{env}}}") == 1
    assert tex.index(r"\toprule") < tex.index(r"\midrule") < tex.index(r"\bottomrule")
    ncols, heads, rows = _latex_parts(tex)
    n_rows = sum(len(b.rows) for b in t.blocks)
    assert len(rows) == n_rows
    for line in heads + rows:
        spans = [int(s) for s in re.findall(r"\\multicolumn\{(\d+)\}", line)]
        assert line.count("&") + 1 - len(spans) + sum(spans) == ncols, line
    md = to_markdown(t)
    table = [line for line in md.splitlines() if line.startswith("|")]
    assert len(table) == 2 + n_rows
    assert len({line.count("|") - line.count("\\|") for line in table}) == 1
    assert re.fullmatch(r"\|(:?-+:?\|)+", table[1])
    assert table[0].count("|") - 1 == ncols


def test_latex_marks_and_missing_cells(built):
    tex = to_latex(built[0]["ablation_components"])
    _, _, rows = _latex_parts(tex)
    cells = [[c.strip() for c in r.split("&")] for r in rows]
    ours_hazy = cells[3]
    assert ours_hazy[0] == "Ours (nimbus-full: csm+plm+ggs)" and all(c.startswith(r"\first{") for c in ours_hazy[2:])
    assert cells[1][2] == r"\second{21.00}"
    assert cells[2][0] == "w/o CSM" and cells[2][2:] == ["--"] * 3
    assert r"\multirow{4}{*}{Hazy (H)}" in tex and tex.count(r"\cmidrule(lr){1-5}") == 2
    assert "% rows -> methods:" in tex and f"Ours = {OURS}" in tex
    ggs = to_latex(built[0]["ablation_ggs"])
    assert ggs.split(r"\bottomrule")[0].count(r"\midrule") == 2  # the paper's rule above "Ours"
    assert r"$M_\text{init}$" in to_latex(built[0]["ablation_minit"])


def test_runtime_values_and_text(built):
    t = built[0]["runtime"]
    assert t.blocks[0].labels == ["nimbus-full", "3dgs", "nimbus-no-ggs", "nimbus-ggs-no-depth", "nimbus-minit-1k",
                         "nimbus-minit-4k"]
    assert t.row("3dgs").values[("", "training_min")] == pytest.approx(2.0)
    assert t.row("3dgs").values[("", "params_M")] == 0.25
    assert t.row("nimbus-no-ggs").values[("", "fps")] is None  # one of two scenes
    params, memory, training, fps = RUNTIME_COLUMNS
    assert params.format(94.1, "-") == "94.1M" and params.format(0.25, "-") == "0.25M"
    assert training.format(29.0, "-") == "29min" and training.format(1.5, "-") == "1.5min"
    assert fps.format(171.0, "-") == "171" and memory.format(None, "-") == "-"
    assert "device: cpu" in t.notes[0] and "no values" in " ".join(t.notes)
    rows = list(csv.DictReader(io.StringIO(to_csv([t]))))
    assert rows[1]["method"] == "3dgs" and float(rows[1]["training_min"]) == pytest.approx(2.0)
    assert rows[2]["fps"] == ""


def test_ablations_csv(built):
    tables = [t for k, t in built[0].items() if k != "runtime"]
    text = to_csv(tables)
    header = text.splitlines()[0].split(",")
    assert len(header) == len(set(header)) and "lpips_net" in header, header
    rows = list(csv.DictReader(io.StringIO(text)))
    ours = [r for r in rows if r["table"] == "ablation_components" and r["weather"] == "H" and r["variant"] == "Ours"]
    assert [r["scene"] for r in ours] == ["garden", "street", "Average"]
    assert float(ours[-1]["psnr"]) == pytest.approx(22.0) and ours[-1]["psnr_mark"] == "best"
    missing = next(r for r in rows if r["variant"] == "w/o CSM" and r["scene"] == "Average")
    assert missing["psnr"] == "" and missing["runs"] == "0"


def test_paper_reference_tables_and_their_marks():
    """The transcribed ablation tables load in our layout; our rule's best is the paper's bold."""
    paper = paper_ablation_tables()
    assert set(paper) == {"ablation_components", "ablation_ggs", "ablation_loss", "ablation_minit", "runtime"}
    comp = paper["ablation_components"]
    assert [len(b.rows) for b in comp.blocks] == [3, 2, 2]  # the paper's rows only
    assert comp.row("Restored-Derived Residuals", 1).values[("Average", "psnr")] == 29.65
    assert paper["runtime"].row("Ours").values[("", "params_M")] == 78.4
    for spec in ABLATIONS:
        rows = list(csv.DictReader((ABLATION_REFERENCE_DIR / spec.reference).open()))
        assert {r["table_label"] for r in rows} == {spec.paper_label}
        groups: dict = {}
        for r in rows:
            groups.setdefault((r["block"], r["scene"]), []).append(r)
        for group in groups.values():
            for k in METRICS:
                marks = rank_marks([float(r[k]) for r in group], HIGHER_IS_BETTER[k], DECIMALS[k])
                assert ["best" if m == 1 else "" for m in marks] == [r[f"{k}_mark"] for r in group]
    for t in paper.values():
        assert "the paper's reported numbers on the paper's data" in to_markdown(t)
        tex = to_latex(t)
        assert "NOT results of this benchmark" in tex and "tab:nimbus-bench-paper-" in tex


def test_presets_are_not_mixed(tmp_path):
    recs = records("tiny") + [dict(r, cell_id=r["cell_id"] + "-fast", preset="fast") for r in records("fast")[:4]]
    tables, _ = ablation_tables(_store(tmp_path, recs))
    keys = [t.key for t in tables]
    assert "ablation_components_tiny" in keys and "ablation_components_fast" in keys
    fast = next(t for t in tables if t.key == "ablation_components_fast")
    assert fast.row(OURS_LABEL, 0).values[("Average", "psnr")] == pytest.approx(22.0) and "preset fast" in fast.title
    assert "ablation_ggs_fast" not in keys  # no GGS-factor row was run with the fast preset


def test_several_devices_are_flagged(tmp_path):
    recs = records() + [dict(records(device="cuda")[-1], cell_id="gpu-3dgs", scene="gpu-scene")]
    tables, _ = ablation_tables(_store(tmp_path, recs))
    runtime = next(t for t in tables if t.key == "runtime")
    assert "several devices (cpu, cuda)" in " ".join(runtime.notes)


def test_tables_command_writes_and_lists(tmp_path, capsys):
    _store(tmp_path / "root", records())
    out = tmp_path / "tables"
    assert run_cli(TOOL.run, ["tables", "--root", str(tmp_path / "root"), "--out", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    for stem in ("ablation_components", "ablation_ggs", "ablation_minit", "runtime"):
        assert {f"{stem}.tex", f"{stem}.md", f"paper_{stem}.tex", f"paper_{stem}.md"} <= names
    assert {"ablations.md", "ablations.csv", "runtime.csv", "weather_H+R+S.tex", "paper_H+R+S.tex"} <= names
    assert not any(n.startswith(("ablation_loss", "paper_ablation_loss")) for n in names)
    listing = capsys.readouterr().out
    assert "ours: Factor-wise ablation of GGS (H+R+S), preset tiny (paper layout tab:ablation_ggs)" in listing
    assert "the paper's reported numbers on the paper's data (tab:runtime" in listing
    assert ("not written (nothing in the store to fill them): margins (no nimbus cell to compare), ablation_loss "
            "(tab:ablation_loss)") in listing
    md = (out / "ablations.md").read_text()
    assert md.index("### Factor-wise ablation of GGS") < md.index("(tab:ablation_ggs: Factor-wise")


def test_refused_store_writes_nothing(tmp_path, capsys):
    recs = records() + [dict(records()[0], cell_id="other", ssim_protocol="dmpix")]
    _store(tmp_path / "root", recs)
    out = tmp_path / "tables"
    assert run_cli(TOOL.run, ["tables", "--root", str(tmp_path / "root"), "--out", str(out)]) == 2
    assert "mixes SSIM protocols" in capsys.readouterr().err and not out.exists()
