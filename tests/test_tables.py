"""Comparison tables from a results store: LaTeX structure, Markdown, CSV, best / second-best marks."""

from __future__ import annotations

import csv
import io
import re

import pytest

from benchmark.cli import TOOL
from benchmark.store import ResultsStore, load_results
from benchmark.tables import ceiling, inputs
from benchmark.tables.comparison import tables as comparison_tables
from benchmark.tables.margins import tables as margins_tables
from benchmark.tables.model import rank_marks
from benchmark.tables.results import ABLATION_OURS, COMPARISON_OURS
from benchmark.tables.summary import summary_text
from benchmark.tables.writer import to_csv, to_latex, to_markdown
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError

# (method, scene, psnr, ssim, lpips): in haze, "nimbus" is best everywhere, "3dgs" second in PSNR,
# "restore+3dgs" second in SSIM and LPIPS; "nimbus" misses street in rain (no Average there).
VALUES = {
    "H": [("nimbus", "garden", 21.0, 0.70, 0.20), ("3dgs", "garden", 18.0, 0.50, 0.40),
          ("restore+3dgs", "garden", 17.0, 0.60, 0.30),
          ("nimbus", "street", 23.0, 0.80, 0.10), ("3dgs", "street", 20.0, 0.60, 0.30),
          ("restore+3dgs", "street", 19.0, 0.70, 0.20)],
    "R": [("nimbus", "garden", 25.0, 0.8, 0.2), ("3dgs", "garden", 24.0, 0.7, 0.3),
          ("3dgs", "street", 22.0, 0.6, 0.3)],
}
#: The label of the per-weather tables' "Ours" row (the ``nimbus`` method).
OURS = COMPARISON_OURS.label


def records(ssim_protocol="3dgs", seeds=(0,)):
    out = []
    for weather, rows in VALUES.items():
        for method, scene, p, s, lp in rows:
            for seed in seeds:
                out.append({"cell_id": f"{scene}-tiny_{weather}_{method}_tiny_s{seed}", "scene": scene,
                            "size": "tiny", "weather": weather, "method": method, "preset": "tiny", "seed": seed,
                            "status": "ok", "psnr": p + seed, "ssim": s, "lpips": lp,
                            "ssim_protocol": ssim_protocol, "lpips_net": "vgg", "train_time_s": 1.0})
    out.append({"cell_id": "garden-tiny_S_3dgs_tiny_s0", "scene": "garden", "size": "tiny", "weather": "S",
                "method": "3dgs", "preset": "tiny", "seed": 0, "status": "error", "error": "boom"})
    return out


#: The clean ceiling (3dgs on the clean views) per scene: two seeds on garden, one on street.
CEILING_VALUES = [("garden", 0, 30.0, 0.90, 0.05), ("garden", 1, 31.0, 0.92, 0.03), ("street", 0, 33.0, 0.95, 0.02)]


def ceiling_records(values=CEILING_VALUES, preset="tiny"):
    return [{"cell_id": f"{scene}-tiny_clean_3dgs_{preset}_s{seed}", "scene": scene, "size": "tiny",
             "weather": "clean", "method": "3dgs", "preset": preset, "seed": seed, "status": "ok", "psnr": p,
             "ssim": s, "lpips": lp, "ssim_protocol": "3dgs", "lpips_net": "vgg", "train_time_s": 1.0}
            for scene, seed, p, s, lp in values]


#: The degraded input's own score per (weather, scene), as a weather cell's record carries it (input_psnr, ...).
INPUT_VALUES = {("H", "garden"): (12.0, 0.40, 0.50), ("H", "street"): (14.0, 0.50, 0.46),
                ("R", "garden"): (20.0, 0.75, 0.25), ("R", "street"): (19.0, 0.70, 0.30)}


def input_records(seeds=(0,)):
    """:func:`records` as cells that score their input write them; street in rain by one method only (3dgs)."""
    return [dict(r, input_psnr=INPUT_VALUES[(r["weather"], r["scene"])][0] + r["seed"] * 0.5,
                 input_ssim=INPUT_VALUES[(r["weather"], r["scene"])][1],
                 input_lpips=INPUT_VALUES[(r["weather"], r["scene"])][2])
            if r["status"] == "ok" else r for r in records(seeds=seeds)]


@pytest.fixture
def ceiling_root(tmp_path):
    store = ResultsStore(tmp_path / "ceiling")
    for r in records() + ceiling_records():
        store.append(r)
    return tmp_path / "ceiling"


@pytest.fixture
def store_root(tmp_path):
    store = ResultsStore(tmp_path)
    for r in records():
        store.append(r)
    return tmp_path


@pytest.fixture
def tables(store_root):
    return {t.layout: t for t in comparison_tables(load_results(store_root), ["nimbus", "3dgs"])[0]}


def test_rank_marks():
    assert rank_marks([1.0, 3.0, 2.0], True, 2) == [None, 1, 2]
    assert rank_marks([0.1, 0.3, 0.2], False, 3) == [1, None, 2]
    assert rank_marks([2.0, 1.0], True, 2) == [1, None]  # no "second best" of two
    assert rank_marks([2.001, 2.0, 1.0], True, 2) == [1, 1, 2]  # equal as printed: both best
    assert rank_marks([None, 2.0, 1.0, float("nan")], True, 2) == [None, 1, None, None]
    assert rank_marks([5.0], True, 2) == [None]


def test_tables_from_store(tables):
    assert list(tables) == ["H", "R"]  # error-only setting S has no table
    h = tables["H"]
    assert h.blocks[0].labels == [OURS, "3dgs", "restore+3dgs"] and h.groups == ["garden", "street", "Average"]
    assert h.row(OURS).values[("Average", "psnr")] == pytest.approx(22.0)
    assert h.marks("Average", "psnr") == [1, 2, None]
    assert h.marks("garden", "ssim") == [1, None, 2]
    assert h.marks("street", "lpips") == [1, None, 2]
    r = tables["R"]
    assert r.row(OURS).values[("Average", "psnr")] is None  # a missing scene leaves the average empty
    assert r.row("3dgs").values[("Average", "psnr")] == pytest.approx(23.0)


def _latex_rows(tex: str) -> list[str]:
    body = tex.split(r"\midrule", 1)[1].split(r"\bottomrule", 1)[0]
    return [row for row in body.split(r"\\") if row.strip()]


def test_ours_row_names_its_method(tables):
    """The per-weather "Ours" row is ``nimbus`` (components by auto) and says so; the note names the
    ablations' Ours too, so the two are not read as one configuration."""
    h = tables["H"]
    assert COMPARISON_OURS.method == "nimbus" and OURS == "Ours (nimbus: components by auto)"
    assert h.row(OURS).fields["method"] == "nimbus"
    assert h.row(OURS).values[("garden", "psnr")] == 21.0  # the nimbus record's value
    note = " ".join(h.notes)
    assert "Ours = nimbus (components by auto)" in note and f"Ours is {ABLATION_OURS.method}" in note
    md = to_markdown(h)
    assert "| Ours (nimbus: components by auto) |" in md and "Ours = nimbus (components by auto)" in md
    assert "Ours (nimbus: components by auto)" in to_latex(h)


def test_ours_row_label_keeps_the_preset(tmp_path):
    store = ResultsStore(tmp_path)
    for r in records() + [dict(r, cell_id=r["cell_id"] + "-fast", preset="fast") for r in records()[:1]]:
        store.append(r)
    h = comparison_tables(load_results(tmp_path), ["nimbus"])[0][0]
    assert {f"{OURS} (tiny)", f"{OURS} (fast)", "3dgs (tiny)"} <= set(h.blocks[0].labels)
    assert h.row(f"{OURS} (fast)").fields["method"] == "nimbus (fast)"


def test_latex_structure_and_marks(tables):
    tex = to_latex(tables["H"])
    for env in ("table*", "tabular"):
        assert tex.count(rf"\begin{{{env}}}") == tex.count(rf"\end{{{env}}}") == 1
    assert tex.count("{") == tex.count("}")
    assert tex.index(r"\toprule") < tex.index(r"\midrule") < tex.index(r"\bottomrule")
    spec = re.search(r"\\begin\{tabular\}\{([^}]*)\}", tex).group(1)
    ncols = len(spec.replace(" ", ""))
    assert ncols == 1 + 3 * 3  # method + (garden, street, Average) x 3 metrics
    header = tex.split(r"\toprule", 1)[1].split(r"\midrule", 1)[0]
    spans = [int(n) for n in re.findall(r"\\multicolumn\{(\d+)\}", header)]
    assert 1 + sum(spans) == ncols
    assert re.findall(r"\\cmidrule\(lr\)\{(\d+)-(\d+)\}", header) == [("2", "4"), ("5", "7"), ("8", "10")]
    assert header.count(r"PSNR$\uparrow$") == 3 and header.count(r"LPIPS$\downarrow$") == 3
    rows = _latex_rows(tex)
    assert len(rows) == 3
    for row in rows:
        assert row.count("&") == ncols - 1
    nimbus, gs, restore = (re.split(r"\s*&\s*", row.strip()) for row in rows)
    assert nimbus[0] == "Ours (nimbus: components by auto)" and restore[0] == "restore+3dgs"
    assert all(c.startswith(r"\first{") for c in nimbus[1:])
    assert gs[1] == r"\second{18.00}" and gs[2] == "0.500" and restore[2] == r"\second{0.600}"
    assert r"\providecommand{\first}[1]{\cellcolor{red!25}{#1}}" in tex
    assert "SSIM protocol: 3dgs" in tex and "lpips-vgg-v0.1" in tex


def test_latex_missing_and_escaped(tables):
    t = tables["R"]
    t.blocks[0].rows[0].label = "nimbus_v2"
    tex = to_latex(t)
    row = _latex_rows(tex)[0].strip()
    assert row.startswith(r"nimbus\_v2")
    assert row.split("&")[-1].strip() == "--"  # no Average LPIPS for a method missing a scene
    assert row.count("&") == 9


def test_markdown_tables(tables):
    md = to_markdown(tables["H"])
    rows = [line for line in md.splitlines() if line.startswith("|")]
    assert {line.count("|") for line in rows} == {10 + 1}  # method + 3 groups x 3 metrics
    assert re.fullmatch(r"\|(:?-+:?\|)+", rows[1])
    cells = [c.strip() for c in rows[2].strip("|").split("|")]
    assert cells[0] == OURS and all(c.startswith("**") for c in cells[1:])
    gs = [c.strip() for c in rows[3].strip("|").split("|")]
    assert gs[1] == "_18.00_" and gs[2] == "0.500"
    assert "SSIM protocol: 3dgs" in md and "LPIPS: lpips-vgg-v0.1" in md


def test_csv(tables):
    text = to_csv(list(tables.values()))
    header = text.splitlines()[0].split(",")
    assert len(header) == len(set(header)), header  # a repeated name hides a column from csv.DictReader / pandas
    rows = list(csv.DictReader(io.StringIO(text)))
    assert len(rows) == 3 * 3 + 2 * 3  # (methods x groups) per weather
    best = [r for r in rows if r["weather"] == "H" and r["scene"] == "Average" and r["psnr_mark"] == "best"]
    assert [r["method"] for r in best] == ["nimbus"] and float(best[0]["psnr"]) == pytest.approx(22.0)
    assert {r["ssim_protocol"] for r in rows} == {"3dgs"} and {r["lpips_net"] for r in rows} == {"lpips-vgg-v0.1"}
    assert all(r["lpips"] == "" or 0 <= float(r["lpips"]) < 1 for r in rows)


def test_the_clean_ceiling_row_and_each_methods_gap_to_it(ceiling_root, tables):
    with_ceiling = {t.layout: t for t in comparison_tables(load_results(ceiling_root), ["nimbus", "3dgs"])[0]}
    assert list(with_ceiling) == ["H", "R"]  # the ceiling is no weather setting: no table of its own
    h = with_ceiling["H"]
    assert [b.name for b in h.blocks] == ["trained on H", ceiling.CEILING_BLOCK, ceiling.GAP_BLOCK]
    assert h.lead == ("Method", "Rows") and h.groups == ["garden", "street", "Average"]
    # The methods' rows and marks are those of the table without a ceiling.
    plain = tables["H"]
    assert [r.values for r in h.blocks[0].rows] == [r.values for r in plain.blocks[0].rows]
    assert all(h.marks(g, k) == plain.marks(g, k) for g in h.groups for k in ("psnr", "ssim", "lpips"))
    # The ceiling: per scene the mean over its seeds, Average over the table's scenes; never marked.
    [c] = h.blocks[1].rows
    assert c.label == ceiling.LABEL == "3DGS (clean views)"
    assert c.values[("garden", "psnr")] == pytest.approx(30.5) and c.values[("garden", "lpips")] == pytest.approx(0.04)
    assert c.values[("street", "ssim")] == pytest.approx(0.95) and c.group_fields["garden"]["seeds"] == 2
    assert c.values[("Average", "psnr")] == pytest.approx((30.5 + 33.0) / 2)
    # Each method's gap: its value minus the ceiling's, every metric, every group.
    gaps = h.blocks[2].rows
    assert [g.label for g in gaps] == h.blocks[0].labels
    for method, gap in zip(h.blocks[0].rows, gaps):
        for key, value in gap.values.items():
            assert value == pytest.approx(method.values[key] - c.values[key]), (method.label, key)
    assert h.row(OURS, 2).values[("garden", "psnr")] == pytest.approx(21.0 - 30.5)
    assert h.row("3dgs", 2).values[("Average", "lpips")] == pytest.approx(0.35 - 0.03)
    for block in (1, 2):
        assert all(m is None for g in h.groups for k in ("psnr", "ssim", "lpips") for m in h.marks(g, k, block))
    # A missing method value leaves its gap (and the gap's Average) empty, never a partial one.
    r = with_ceiling["R"]
    assert r.row(OURS, 2).values[("street", "psnr")] is None and r.row(OURS, 2).values[("Average", "psnr")] is None
    assert r.row("3dgs", 2).values[("street", "psnr")] == pytest.approx(22.0 - 33.0)
    # Markdown and LaTeX show the blocks by name; the note says what the rows are.
    md = to_markdown(h)
    assert "| 3DGS (clean views) | clean ceiling | 30.50 | 0.910 | 0.040 |" in md
    assert "| 3dgs | gap to ceiling | -12.50 | -0.410 | 0.360 |" in md
    assert "clean ceiling: 3dgs trained on the scene's clean training views" in " ".join(h.notes)
    tex = to_latex(h)
    assert r"\multirow{1}{*}{clean ceiling}" in tex
    assert tex.count(r"\first{") == to_latex(plain).count(r"\first{") == 9  # only the methods' marks
    # The CSV keeps the measured values: the ceiling's lines, not the derived gaps.
    lines = list(csv.DictReader(io.StringIO(to_csv(list(with_ceiling.values())))))
    assert len(lines) == len(list(csv.DictReader(io.StringIO(to_csv(list(tables.values())))))) + 2 * 3
    clean = [x for x in lines if x["method"] == ceiling.LABEL]
    assert {(x["weather"], x["scene"]) for x in clean} == {(w, g) for w in "HR" for g in ("garden", "street",
                                                                                                  "Average")}
    assert all(x["psnr_mark"] == "" for x in clean) and float(clean[0]["psnr"]) == pytest.approx(30.5)


def test_no_ceiling_record_no_ceiling_row_and_no_word_of_it(tables, store_root):
    for t in tables.values():
        assert len(t.blocks) == 1 and t.lead == ("Method",)
        assert "ceiling" not in to_markdown(t) and "clean views" not in to_markdown(t)
    [m], _ = margins_tables(load_results(store_root), ["nimbus", "3dgs"])
    assert ceiling.LABEL not in m.groups and "ceiling" not in to_markdown(m)
    assert "ΔPSNR" not in summary_text(load_results(store_root)) and "ceiling" not in \
        summary_text(load_results(store_root))


def test_records_without_the_input_score_show_no_input_row_and_no_word_of_it(tables, store_root):
    for t in tables.values():
        text = to_markdown(t) + to_latex(t) + to_csv([t])
        assert inputs.LABEL not in text and inputs.BLOCK not in text and "degraded input" not in text
    assert "Input" not in summary_text(load_results(store_root))


def test_the_degraded_input_row(tmp_path, tables):
    """Its own unranked block under the methods: per scene the mean over the records carrying it, Average over
    the table's scenes; the methods' rows and marks are untouched."""
    store = ResultsStore(tmp_path)
    for r in input_records(seeds=(0, 1)) + ceiling_records():
        store.append(r)
    got = {t.layout: t for t in comparison_tables(load_results(tmp_path), ["nimbus", "3dgs"])[0]}
    h = got["H"]
    assert [b.name for b in h.blocks] == ["trained on H", inputs.BLOCK, ceiling.CEILING_BLOCK, ceiling.GAP_BLOCK]
    [row] = h.blocks[1].rows
    assert row.label == inputs.LABEL == "degraded input (test views)"
    # garden: every method and both seeds carry it (12.0 and 12.5): their mean; street alike (14.0, 14.5).
    assert row.values[("garden", "psnr")] == pytest.approx(12.25)
    assert row.values[("street", "ssim")] == pytest.approx(0.50)
    assert row.values[("street", "lpips")] == pytest.approx(0.46)
    assert row.values[("Average", "psnr")] == pytest.approx((12.25 + 14.25) / 2)
    assert row.values[("Average", "lpips")] == pytest.approx((0.50 + 0.46) / 2)
    assert all(m is None for g in h.groups for k in ("psnr", "ssim", "lpips") for m in h.marks(g, k, 1))
    # The methods: the values of the table without the input (mean over two seeds: +0.5 PSNR), the same marks.
    plain = tables["H"]
    for mine, theirs in zip(h.blocks[0].rows, plain.blocks[0].rows):
        assert mine.label == theirs.label and mine.values[("garden", "ssim")] == theirs.values[("garden", "ssim")]
        assert mine.values[("garden", "psnr")] == pytest.approx(theirs.values[("garden", "psnr")] + 0.5)
    assert all(h.marks(g, k) == plain.marks(g, k) for g in h.groups for k in ("psnr", "ssim", "lpips"))
    # The ceiling block and the gaps still measure the methods against the ceiling, not against the input.
    assert h.row(OURS, 3).values[("garden", "psnr")] == pytest.approx(21.5 - 30.5)
    # Rain: street has a 3dgs cell only (nimbus misses it), whose record carries the input: a value and an Average.
    r = got["R"].blocks[1].rows[0]
    assert r.values[("street", "psnr")] == pytest.approx(19.25)
    assert r.values[("Average", "ssim")] == pytest.approx(0.725)
    # Markdown, LaTeX and the note show it by name, unmarked; the CSV keeps its measured lines.
    md = to_markdown(h)
    assert "| degraded input (test views) | no reconstruction | 12.25 | 0.400 | 0.500 | 14.25 | 0.500 | 0.460 |" in md
    assert "degraded input (test views) = the setting's degraded test views themselves" in md
    assert r"\multirow{1}{*}{no reconstruction}" in to_latex(h)
    assert to_latex(h).count(r"irst{") == to_latex(plain).count(r"irst{")
    lines = [x for x in csv.DictReader(io.StringIO(to_csv(list(got.values())))) if x["method"] == inputs.LABEL]
    assert [(x["weather"], x["scene"]) for x in lines] == [(w, g) for w in "HR" for g in ("garden", "street",
                                                                                               "Average")]
    assert float(lines[0]["psnr"]) == pytest.approx(12.25) and all(x["psnr_mark"] == "" for x in lines)


def test_the_input_row_of_a_scene_no_record_carries_is_empty(tmp_path):
    """A scene whose records all predate the fields has no input value, and the Average none (never a partial one)."""
    store = ResultsStore(tmp_path)
    for r in input_records():
        store.append(r if r["scene"] == "garden" else {k: v for k, v in r.items() if not k.startswith("input_")})
    h = comparison_tables(load_results(tmp_path))[0][0]
    row = h.row(inputs.LABEL, 1)
    assert row.values[("garden", "psnr")] == pytest.approx(12.0) and row.values[("street", "psnr")] is None
    assert row.values[("Average", "psnr")] is None
    assert h.blocks[0].name == "trained on H" and len(h.blocks) == 2


def test_a_method_meets_the_ceiling_of_its_own_preset(tmp_path):
    store = ResultsStore(tmp_path)
    fast = [dict(r, cell_id=r["cell_id"] + "-fast", preset="fast") for r in records()[:2]]  # nimbus, 3dgs garden H
    for r in records() + fast + ceiling_records([("garden", 0, 40.0, 0.99, 0.01)], preset="fast"):
        store.append(r)
    h = comparison_tables(load_results(tmp_path), ["nimbus", "3dgs"])[0][0]
    [c] = h.blocks[1].rows
    assert c.label == "3DGS (clean views) (fast)"
    # Only the fast rows have a gap: the tiny ones have no tiny ceiling to meet.
    assert h.blocks[2].labels == [f"{OURS} (fast)", "3dgs (fast)"]
    assert h.row("3dgs (fast)", 2).values[("garden", "psnr")] == pytest.approx(18.0 - 40.0)
    assert c.values.get(("street", "psnr")) is None and h.row("3dgs (fast)", 2).values[("Average", "psnr")] is None


def test_seeds_are_averaged_and_mixed_protocols_refused(tmp_path):
    store = ResultsStore(tmp_path / "a")
    for r in records(seeds=(0, 1)):
        store.append(r)
    (h, _), _ = comparison_tables(load_results(tmp_path / "a"))
    assert h.row(OURS).values[("garden", "psnr")] == pytest.approx(21.5)
    assert h.row(OURS).group_fields["garden"]["seeds"] == 2
    store = ResultsStore(tmp_path / "b")
    for r in records() + [dict(records("dmpix")[0], cell_id="other")]:
        store.append(r)
    with pytest.raises(NimbusError, match="mixes SSIM protocols"):
        comparison_tables(load_results(tmp_path / "b"))


def test_margins_say_where_ours_wins_and_by_how_much(store_root):
    store = ResultsStore(store_root)
    # A method that beats nimbus on garden haze (PSNR +1, SSIM +0.05, LPIPS -0.05) and has nothing else.
    store.append({**records()[0], "cell_id": "garden-tiny_H_medium_tiny_s0", "method": "medium", "psnr": 22.0,
                  "ssim": 0.75, "lpips": 0.15})
    [t], skipped = margins_tables(load_results(store_root), ["nimbus", "3dgs"])
    assert skipped == [] and t.groups == ["3dgs", "restore+3dgs", "medium"]
    assert [r.label for r in t.blocks[0].rows] == ["H", "R", "All"]
    h, r, everything = (t.row(x).values for x in ("H", "R", "All"))
    # Haze, both scenes: nimbus 21 / 23 against 3dgs 18 / 20 (SSIM +0.2, LPIPS 0.2 lower), restore 17 / 19.
    assert h[("3dgs", "d_psnr")] == pytest.approx(3.0) and h[("3dgs", "wins")] == "2/2"
    assert h[("3dgs", "d_ssim")] == pytest.approx(0.2) and h[("3dgs", "d_lpips")] == pytest.approx(0.2)
    assert h[("restore+3dgs", "d_psnr")] == pytest.approx(4.0)
    # A loss is negative on every metric and not won.
    assert h[("medium", "d_psnr")] == pytest.approx(-1.0) and h[("medium", "wins")] == "0/1"
    assert h[("medium", "d_ssim")] == pytest.approx(-0.05) and h[("medium", "d_lpips")] == pytest.approx(-0.05)
    # Rain: nimbus has garden only, so street (3dgs alone) is not compared; restore has no rain cell.
    assert r[("3dgs", "d_psnr")] == pytest.approx(1.0) and r[("3dgs", "wins")] == "1/1"
    assert ("restore+3dgs", "d_psnr") not in r
    assert everything[("3dgs", "d_psnr")] == pytest.approx(7 / 3) and everything[("3dgs", "wins")] == "3/3"
    assert everything[("medium", "wins")] == "0/1"
    lines = list(csv.DictReader(io.StringIO(to_csv([t]))))
    medium_h = next(x for x in lines if x["weather"] == "H" and x["other"] == "medium")
    assert (medium_h["won"], medium_h["scenes"], float(medium_h["d_psnr"])) == ("0", "1", -1.0)
    # Nothing to compare: no nimbus cell, or nimbus alone.
    only = ResultsStore(store_root / "only")
    for rec in records():
        if rec["method"] in ("3dgs",):
            only.append(rec)
    assert margins_tables(load_results(store_root / "only"))[0] == []
    alone = ResultsStore(store_root / "alone")
    for rec in records():
        if rec["method"] == "nimbus":
            alone.append(rec)
    tabs, skipped = margins_tables(load_results(store_root / "alone"))
    assert tabs == [] and "no method besides nimbus" in skipped[0]


def test_margins_seed_spread(tmp_path, store_root):
    """With several training seeds, ±seed is the sd over seeds of the per-seed ΔPSNR; one seed: no column."""
    assert "d_psnr_seed_sd" not in [c.key for c in margins_tables(load_results(store_root))[0][0].columns]
    store = ResultsStore(tmp_path / "seeds")
    recs = records(seeds=(0, 1, 2))  # every method's PSNR rises by 1 per seed: constant margins
    for r in recs:
        store.append(r)
    # "noisy" on garden haze: nimbus 21 + k against 20 + k + e_k, e = (0.5, -0.5, 0): margins 0.5, 1.5, 1.0.
    for k, e in enumerate((0.5, -0.5, 0.0)):
        store.append({**recs[0], "cell_id": f"garden-tiny_H_noisy_tiny_s{k}", "method": "noisy", "seed": k,
                      "psnr": 20.0 + k + e})
    # "few" has one seed only: no spread for it anywhere.
    store.append({**recs[0], "cell_id": "garden-tiny_H_few_tiny_s0", "method": "few", "psnr": 19.0})
    [t], _ = margins_tables(load_results(tmp_path / "seeds"), ["nimbus", "3dgs"])
    assert t.columns[-1].key == "d_psnr_seed_sd"
    h = t.row("H").values
    assert h[("noisy", "d_psnr")] == pytest.approx(1.0) and h[("noisy", "d_psnr_seed_sd")] == pytest.approx(0.5)
    assert h[("3dgs", "d_psnr_seed_sd")] == pytest.approx(0.0, abs=1e-9)
    assert h[("few", "d_psnr_seed_sd")] is None
    lines = list(csv.DictReader(io.StringIO(to_csv([t]))))
    noisy = next(x for x in lines if x["weather"] == "H" and x["other"] == "noisy")
    few = next(x for x in lines if x["weather"] == "H" and x["other"] == "few")
    assert (noisy["seeds"], float(noisy["d_psnr_seed_sd"])) == ("3", 0.5)
    assert (few["seeds"], few["d_psnr_seed_sd"]) == ("1", "")
    assert "±seed" in to_markdown(t) and "/ sqrt(n)" in t.notes[0]


def test_margins_add_ours_gap_to_the_clean_ceiling(ceiling_root):
    [t], _ = margins_tables(load_results(ceiling_root), ["nimbus", "3dgs"])
    assert t.groups == ["3dgs", "restore+3dgs", ceiling.LABEL]  # the ceiling is no method: its 3dgs is not "3dgs"
    h, r, everything = (t.row(x).values for x in ("H", "R", "All"))
    assert h[("3dgs", "d_psnr")] == pytest.approx(3.0)  # unchanged by the ceiling's 3dgs records
    # Haze: nimbus 21 / 23 against the ceiling's 30.5 / 33; LPIPS in margins' sign (the other minus Ours).
    assert h[(ceiling.LABEL, "d_psnr")] == pytest.approx(((21 - 30.5) + (23 - 33)) / 2)
    assert h[(ceiling.LABEL, "d_lpips")] == pytest.approx(((0.04 - 0.2) + (0.02 - 0.1)) / 2)
    assert h[(ceiling.LABEL, "wins")] == "0/2" and r[(ceiling.LABEL, "wins")] == "0/1"
    assert everything[(ceiling.LABEL, "d_psnr")] == pytest.approx(((21 - 30.5) + (23 - 33) + (25 - 30.5)) / 3)
    assert "clean ceiling" in " ".join(t.notes)
    # nimbus alone with a ceiling: the margins still have something to say.
    alone = ResultsStore(ceiling_root / "alone")
    for rec in [x for x in records() if x["method"] == "nimbus"] + ceiling_records():
        alone.append(rec)
    [t], skipped = margins_tables(load_results(ceiling_root / "alone"))
    assert skipped == [] and t.groups == [ceiling.LABEL]


def test_summary_gives_each_line_its_gap_to_the_ceiling(ceiling_root):
    lines = summary_text(load_results(ceiling_root), ["nimbus", "3dgs"]).splitlines()
    cols = [re.split(r"\s{2,}", line.strip()) for line in lines]
    head = cols[0]
    assert head[:2] == ["Weather", "Method"] and head[-1] == "ΔPSNR vs clean"
    first = dict(zip(head, cols[1]))
    assert (first["Weather"], first["Method"], first["Cells"]) == ("clean", ceiling.LABEL, "3")
    assert first["PSNR↑"] == f"{(30 + 31 + 33) / 3:.2f}" and first["ΔPSNR vs clean"] == "n/a"  # no gap of its own
    rows = {tuple(c[:2]): dict(zip(head, c)) for c in cols[2:] if c[0] in ("H", "R", "S")}
    # Per cell: its PSNR minus its scene's ceiling (garden 30.5, street 33), then the mean over the line's cells.
    assert float(rows[("H", "nimbus")]["ΔPSNR vs clean"]) == pytest.approx(((21 - 30.5) + (23 - 33)) / 2, abs=0.005)
    assert float(rows[("R", "3dgs")]["ΔPSNR vs clean"]) == pytest.approx(((24 - 30.5) + (22 - 33)) / 2, abs=0.005)
    assert rows[("S", "3dgs")]["ΔPSNR vs clean"] == "n/a"  # an error cell: no PSNR, no gap
    assert "ΔPSNR vs clean = the mean over a row's finished cells of the cell's PSNR minus" in lines[-1]


def test_summary_gives_each_line_its_inputs_psnr(tmp_path):
    store = ResultsStore(tmp_path)
    for r in input_records() + ceiling_records():
        store.append(r)
    lines = summary_text(load_results(tmp_path), ["nimbus", "3dgs"]).splitlines()
    cols = [re.split(r"\s{2,}", line.strip()) for line in lines]
    head = cols[0]
    assert head[-2:] == ["Input PSNR", "ΔPSNR vs clean"]
    rows = {tuple(c[:2]): dict(zip(head, c)) for c in cols[1:] if c[0] in ("clean", "H", "R", "S")}
    assert rows[("clean", ceiling.LABEL)]["Input PSNR"] == "n/a"  # trained on the clean views: no degraded input
    # The mean over the line's cells (garden and street): the same for every method of a setting and scene set.
    assert rows[("H", "nimbus")]["Input PSNR"] == rows[("H", "3dgs")]["Input PSNR"] == "13.00"
    assert rows[("R", "nimbus")]["Input PSNR"] == "20.00" and rows[("R", "3dgs")]["Input PSNR"] == "19.50"
    assert rows[("S", "3dgs")]["Input PSNR"] == "n/a"  # an error cell: nothing scored
    assert any(line.startswith("Input PSNR = the degraded test views' own PSNR") for line in lines)
    # A line with a cell that lacks it (an older record) shows none rather than a mean over part of its scenes.
    store.append({k: v for k, v in input_records()[0].items() if not k.startswith("input_")})
    lines = summary_text(load_results(tmp_path), ["nimbus", "3dgs"]).splitlines()
    nimbus_h = next(re.split(r"\s{2,}", line.strip()) for line in lines if line.startswith("H ") and "nimbus" in line)
    assert dict(zip(head, nimbus_h))["Input PSNR"] == "n/a"


def test_summary_table_counts_errors(store_root):
    text = summary_text(load_results(store_root), ["nimbus", "3dgs"])
    lines = text.splitlines()
    s_row = next(line for line in lines if line.startswith("S "))
    assert s_row.split()[-1] == "1" and "n/a" in s_row
    h_rows = [line.split() for line in lines if line.startswith("H ")]
    assert [r[1] for r in h_rows] == ["nimbus", "3dgs", "restore+3dgs"]
    assert float(h_rows[0][2]) == pytest.approx(22.0)  # weather, method, then PSNR


def test_tables_command(store_root, tmp_path, capsys):
    out = tmp_path / "tables"
    assert run_cli(TOOL.run, ["tables", "--root", str(store_root), "--out", str(out),
                              "--parquet", str(tmp_path / "r.parquet")]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["comparisons.csv", "comparisons.md", "margins.csv", "margins.md", "margins.tex", "paper_H.md",
                     "paper_H.tex", "paper_R.md", "paper_R.tex", "provenance.csv", "provenance.md", "provenance.tex",
                     "weather_H.md", "weather_H.tex", "weather_R.md", "weather_R.tex"]
    md = (out / "comparisons.md").read_text()
    assert md.index("### haze (H)") < md.index("### the paper's reported numbers on the paper's data (tab:dehaze")
    assert md.index("### rain (R)") < md.index("against each other method")  # the margins follow the comparisons
    assert md.index("against each other method") < md.index("### Where the figures were made")  # then provenance
    paper_tex = (out / "paper_H.tex").read_text()
    assert "NOT results of this benchmark" in paper_tex and r"\first{21.84}" in paper_tex
    rows = _latex_rows(paper_tex)
    assert len(rows) == 4 and all(r.count("&") == 15 for r in rows)  # 4 scenes + Average
    import pandas as pd

    assert len(pd.read_parquet(tmp_path / "r.parquet")) == len(records())
    assert run_cli(TOOL.run, ["tables", "--root", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert "nimbus-bench run" in capsys.readouterr().err


def test_reference_check_and_update(store_root, tmp_path, capsys):
    ref = tmp_path / "ref.json"
    base = ["reference", "--root", str(store_root), "--reference", str(ref)]
    assert run_cli(TOOL.run, ["reference", "check"] + base[1:]) == 2  # no reference yet: a clear error
    store = ResultsStore(store_root)
    for r in records():  # the cells need input hashes and config hashes, as real records have
        if r["status"] == "ok":
            store.append(dict(r, input_sha256="a" * 64, config_hash="c" * 64))
    assert run_cli(TOOL.run, ["reference", "update"] + base[1:]) == 0
    assert run_cli(TOOL.run, ["reference", "check"] + base[1:]) == 0
    worse = records()[0]
    store.append(dict(worse, psnr=worse["psnr"] - 1.0, input_sha256="b" * 64, config_hash="c" * 64))
    capsys.readouterr()
    assert run_cli(TOOL.run, ["reference", "check"] + base[1:]) == 1
    out = capsys.readouterr().out
    # Inputs are compared by content (tests/test_regression.py); this store has no data folders, so a changed
    # hash is shown in the diff table but is not by itself a problem: the PSNR drop is.
    assert f"{worse['cell_id']}: psnr 20.0000 is worse than the reference 21.0000" in out
    assert "bytes differ" in out and "1 problem(s)" in out


def test_paper_reference_tables_and_their_marks():
    """The transcribed paper tables are complete, and our best / second-best rule reproduces the paper's marks."""
    from benchmark.data import PAPER_DIR as folder
    from benchmark.tables.results import METRIC_COLUMNS

    labels = {}
    disagree = []
    for f in sorted(folder.glob("*.csv")):
        rows = list(csv.DictReader(f.open()))
        labels[rows[0]["table_label"]] = rows[0]["weather"]
        by_scene: dict[str, list[dict]] = {}
        for r in rows:
            by_scene.setdefault(r["scene"], []).append(r)
        assert list(by_scene)[-1] == "Average" and len({len(v) for v in by_scene.values()}) == 1
        for scene, scene_rows in by_scene.items():
            for k in ("psnr", "ssim", "lpips"):
                col = next(c for c in METRIC_COLUMNS if c.key == k)
                marks = rank_marks([float(r[k]) for r in scene_rows], col.higher_is_better, col.decimals)
                if [{1: "best", 2: "second"}.get(m, "") for m in marks] != [r[f"{k}_mark"] for r in scene_rows]:
                    disagree.append((rows[0]["table_label"], scene, k))
    assert labels == {"tab:dehaze": "H", "tab:derain": "R", "tab:desnow": "S", "tab:mix": "H+R+S",
                      "tab:h+r": "H+R", "tab:h+s": "H+S", "tab:r+s": "R+S"}
    # The paper's one slip (README): it marks RainyScape's 0.808 second, above OR+3DGS's 0.814.
    assert disagree == [("tab:r+s", "Tanabata", "ssim")]


def test_a_table_layout_is_data():
    """A hand-built table (two blocks, a text column, an unranked column) renders alike in all three formats."""
    from benchmark.tables.model import Block, Column, LongFormat, Row, Table

    cols = (Column("note", "note", "note", align="left"), Column("psnr", "PSNR↑", r"PSNR$\uparrow$", 2, True),
            Column("mb", "MB", "MB", 0, unit=" MB"))
    fmt = LongFormat("x.csv", "test", ("table", "block", "row", "scene", "note", "psnr", "psnr_mark", "mb"),
                     group_field="scene")

    def row(label, a, b, note="ok"):
        return Row(label, {("a", "psnr"): a, ("b", "psnr"): b, ("a", "note"): note, ("b", "mb"): 512.4},
                   fields={"row": label})

    t = Table("x", "x", "A test of 50% & more", cols, ["a", "b"],
              [Block([row("r_1", 1.0, 2.0), row("r2", 3.0, None, "a|b"), row("r3", 2.0, 1.0)], "first",
                     {"block": "1"}),
               Block([row("s1", 5.0, 5.0)], "second", {"block": "2"})],
              lead=("Row", "Kind"), notes=["n1"], label="tab:x", csv=fmt, fields={"table": "x"})
    assert t.marks("a", "psnr", 0) == [None, 1, 2] and t.marks("a", "mb", 0) == [None] * 3
    assert t.marks("a", "psnr", 1) == [None]  # one row: nothing to rank
    tex = to_latex(t)
    assert tex.count("{") == tex.count("}") and r"\begin{tabular}{l c ccc ccc}" in tex
    rows = _latex_rows(tex)
    assert len(rows) == 4 and all(r.count("&") == 1 + 1 + 6 - 1 for r in rows)
    assert r"r\_1 & \multirow{3}{*}{first}" in rows[0] and r"\first{3.00}" in rows[1] and "512 MB" in rows[0]
    assert r"\cmidrule(lr){1-8}" in tex and r"A test of 50\% \& more" in tex
    md = to_markdown(t)
    table = [line for line in md.splitlines() if line.startswith("|")]
    assert table[0] == "| Row | Kind | a note | a PSNR↑ | a MB | b note | b PSNR↑ | b MB |"
    assert table[1] == "|:---|:---|:---|---:|---:|:---|---:|---:|"
    assert "| r2 | first | a\\|b | **3.00** | – | – | – | 512 MB |" in table
    assert md.rstrip().endswith("n1. Best **bold**, second best _italic_.")
    lines = list(csv.DictReader(io.StringIO(to_csv([t]))))
    assert len(lines) == 2 * 4  # (groups) x (rows)
    assert lines[1] == {"table": "x", "block": "1", "row": "r2", "scene": "a", "note": "a|b", "psnr": "3.0",
                        "psnr_mark": "best", "mb": ""}


def test_reference_data_is_declared_package_data():
    """Every file of benchmark/data ships with a (non-editable) install: pyproject.toml declares it."""
    import fnmatch
    from pathlib import Path

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    from benchmark import reference
    from benchmark.data import DATA_DIR, PAPER_ABLATIONS_DIR, PAPER_DIR, REGRESSION_REFERENCE

    root = Path(__file__).resolve().parents[1]
    patterns = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    declared = patterns["benchmark.data"]
    files = [p.relative_to(DATA_DIR).as_posix() for p in DATA_DIR.rglob("*")
             if p.is_file() and p.suffix not in (".py", ".pyc")]
    assert files and all(any(fnmatch.fnmatch(f, pat) for pat in declared) for f in files), (files, declared)
    # `nimbus-bench reference check / update --regression` read and rewrite this package file.
    assert reference.REGRESSION_REFERENCE == REGRESSION_REFERENCE and REGRESSION_REFERENCE.is_file()
    assert len(list(PAPER_DIR.glob("*.csv"))) == 7
    assert len(list(PAPER_ABLATIONS_DIR.glob("*.csv"))) == 5


def test_a_cell_trained_with_overrides_is_its_own_row_never_averaged_into_the_method(tmp_path):
    from benchmark.store import load_results

    store = ResultsStore(tmp_path)
    base = {"scene": "street", "size": "small", "weather": "H", "method": "nimbus", "preset": "fast", "seed": 0,
            "status": "ok", "ssim": 0.8, "lpips": 0.1, "ssim_protocol": "3dgs", "lpips_net": "vgg"}
    store.append({**base, "cell_id": "street-small_H_nimbus_fast_s0", "psnr": 22.93})
    store.append({**base, "cell_id": "street-small_H_nimbus_fast_s0_c7a2b848", "psnr": 19.58,
                  "overrides": {"lambda_dehaze": "0", "airlight": "constant"}})
    df = load_results(tmp_path)
    assert sorted(df["method"]) == ["nimbus", "nimbus[airlight=constant,lambda_dehaze=0]"]
    assert df.set_index("method")["psnr"]["nimbus"] == 22.93
    assert run_cli(TOOL.run, ["tables", "--root", str(tmp_path), "--out", str(tmp_path / "t")]) == 0
    table = (tmp_path / "t" / "weather_H.md").read_text()
    assert "| 22.93 |" in table.replace("**", "") and "nimbus[airlight=constant,lambda_dehaze=0]" in table
