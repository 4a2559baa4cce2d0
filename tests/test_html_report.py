"""The HTML report (``nimbus-bench report``, benchmark/html_report.py) of a tiny store.

The store is a 2-cell grid (3DGS and NimbusGS, a few iterations, the tiny garden in haze) run in
this process; the report must reference only files that exist, parse, show the store's numbers,
and (where headless Chromium is installed) render to a page that is not blank.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser
from urllib.parse import unquote

import numpy as np
import pytest

from benchmark.cell import CellOptions
from benchmark.cli import TOOL
from benchmark.grid import InlineExecutor, build_cells, run_grid
from benchmark.html_report import PAGE, ReportOptions, build_report, evenly_spaced, reproduce_commands
from benchmark.store import ResultsStore, load_results
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError


class Page(HTMLParser):
    """Every referenced file, and the summary table's rows (its first table) as text."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []
        self.tables = 0
        self.summary: list[list[str]] = []
        self._in_summary = False
        self._cell: list[str] | None = None
        self.ids: set[str] = set()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            self.ids.add(a["id"])
        for key in ("src", "href", "data-thumb", "data-diff"):
            if a.get(key) and not a[key].startswith("#"):
                self.refs.append(a[key])
        if tag == "table":
            self.tables += 1
            self._in_summary = self.tables == 1
        if self._in_summary and tag == "tr":
            self.summary.append([])
        if self._in_summary and tag == "td":
            self._cell = []

    def handle_endtag(self, tag):
        if tag == "table":
            self._in_summary = False
        if tag == "td" and self._cell is not None:
            self.summary[-1].append("".join(self._cell).strip())
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    cells = build_cells(["garden"], ["H"], ["3dgs", "nimbus"], ["tiny"], [0], "tiny", {"iterations": "6"})
    outcome = run_grid(cells, root, InlineExecutor(), CellOptions(lpips_net=None), progress=False,
                       log=lambda s: None)
    assert [r["status"] for r in outcome.ran] == ["ok", "ok"], [r.get("error") for r in outcome.ran]
    # What `nimbus-bench tradeoff` / `stability` leave in a root, so the report shows them.
    (root / "tradeoff").mkdir()
    (root / "tradeoff" / "tradeoff.csv").write_text("knob,value,psnr\niterations,6,12.5\niterations,12,13.25\n")
    shutil.copyfile(next((root / "data").rglob("clean/*.png")), root / "tradeoff" / "tradeoff.png")
    (root / "stability").mkdir()
    (root / "stability" / "stability.csv").write_text("case,method,verdict\nno_haze,3dgs,ok\n")
    return root


@pytest.fixture(scope="module")
def report(store, tmp_path_factory):
    out = tmp_path_factory.mktemp("rep") / "report"
    page = build_report(store, out, ReportOptions(method_order=("nimbus", "3dgs")), command="nimbus-bench report")
    parser = Page()
    parser.feed(page.read_text(encoding="utf-8"))
    parser.close()
    return out, page, parser


def test_every_referenced_file_exists_and_the_page_has_every_section(store, report):
    out, page, parser = report
    assert page == out / PAGE
    assert {"summary", "views", "nimbus", "tradeoff", "stability", "provenance", "diff", "lightbox"} <= parser.ids
    assert parser.refs, "the page references no image"
    for ref in parser.refs:
        assert "://" not in ref, f"the page must not reach the network: {ref}"
        assert (out / unquote(ref)).is_file(), ref
    thumbs = [r for r in parser.refs if r.startswith("images/")]
    # 2 test views x (input, 2 renders, clean) + their diffs (input, renders), 3 x 5 decomposition panels, plot
    assert len(set(thumbs)) == 2 * 4 + 2 * 3 + 15 + 1
    assert any("../" in r and "renders/test" in r for r in parser.refs)  # full size: links into the store
    assert not (out / "images" / "full").exists()
    html = page.read_text(encoding="utf-8")
    assert "Component decision (auto)" in html and "haze_evidence.present" in html
    assert "nimbus-bench run --scenes garden --weathers H --methods 3dgs,nimbus --preset tiny --seeds 0" in html
    assert "--set iterations=6" in html and "no_haze" in html and "12.5" in html


def test_summary_numbers_equal_the_store(store, report):
    _, page, parser = report
    df = load_results(store)
    rows = {(r[0], r[1]): r for r in parser.summary if r}
    assert set(rows) == {("H", "nimbus"), ("H", "3dgs")}
    assert list(rows) == [("H", "nimbus"), ("H", "3dgs")]  # --methods order
    for (w, m), cells in rows.items():
        g = df[(df["weather"] == w) & (df["method"] == m)]
        assert cells[2] == f"{g['psnr'].mean():.2f}"
        assert cells[3] == f"{g['ssim'].mean():.3f}"
        assert cells[4] == "–"  # LPIPS not computed
        assert cells[5] == f"{g['train_time_s'].mean():.1f}"
        assert cells[6:8] == ["1", "0"]
        assert cells[8] == f"{g['input_psnr'].mean():.2f}"  # the degraded input's own PSNR: what the row has to beat
    assert "Input PSNR = the degraded test views" in page.read_text(encoding="utf-8")  # the note under it


def test_per_view_captions_are_the_records_psnr(store, report):
    out, page, _ = report
    html = page.read_text(encoding="utf-8")
    for rec in load_results(store)["record"]:
        for v in rec["per_view"]:
            assert f"{v['psnr']:.2f} dB" in html


def test_copy_full_makes_a_portable_report(store, tmp_path):
    page = build_report(store, tmp_path / "r", ReportOptions(views=1, copy_full=True))
    parser = Page()
    parser.feed(page.read_text(encoding="utf-8"))
    refs = [unquote(r) for r in parser.refs]
    assert refs and all(not r.startswith("..") for r in refs)
    assert all((tmp_path / "r" / r).is_file() for r in refs)


def test_refusals_leave_the_store_alone(store, tmp_path, capsys):
    before = (store / "results.jsonl").read_bytes()
    assert run_cli(TOOL.run, ["report", "--root", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0] and "nimbus-bench run" in err[0]
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "results.jsonl").write_text("")
    assert run_cli(TOOL.run, ["report", "--root", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "empty" in capsys.readouterr().err
    for bad in (store, store / "runs", store / "runs" / "x"):
        with pytest.raises(NimbusError, match="input"):
            build_report(store, bad, overwrite=True)
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "keep.txt").write_text("x")
    with pytest.raises(NimbusError, match="--overwrite"):
        build_report(store, tmp_path / "used")
    assert (tmp_path / "used" / "keep.txt").is_file()
    assert (store / "results.jsonl").read_bytes() == before
    assert not (tmp_path / "o").exists()


def test_reproduce_commands_run_exactly_the_cells():
    def rec(scene, weather, method, seed=0):
        return {"scene": scene, "weather": weather, "method": method, "seed": seed, "size": "tiny",
                "preset": "tiny", "overrides": {}, "ssim_protocol": "3dgs", "lpips_net": None}

    recs = [rec("garden", "H", "3dgs"), rec("garden", "H", "nimbus"), rec("street", "H", "3dgs"),
            rec("street", "H", "nimbus"), rec("garden", "R", "3dgs"), rec("garden", "R", "nimbus", seed=1)]
    cmds = reproduce_commands(recs, "r")
    covered = set()
    for c in cmds:
        words = c.split()
        get = {words[i]: words[i + 1].split(",") for i in range(2, len(words) - 1, 2)}
        covered |= {(s, w, m, int(seed)) for s in get["--scenes"] for w in get["--weathers"]
                    for m in get["--methods"] for seed in get["--seeds"]}
    assert covered == {(r["scene"], r["weather"], r["method"], r["seed"]) for r in recs}
    assert "--scenes garden,street --weathers H --methods 3dgs,nimbus" in cmds[0]
    # No ceiling cell in the store: every command says --no-ceiling (a plain run would add them).
    assert all(c.endswith(" --no-ceiling") for c in cmds)
    # The ceiling of garden and street, seed 0: a command without --no-ceiling runs only ceiling cells the store has
    # (garden R nimbus, seed 1, must say --no-ceiling), and together they run all of them.
    ceilings = {("garden", 0), ("street", 0)}
    cmds = reproduce_commands(recs + [rec(sc, "clean", "3dgs", seed) for sc, seed in ceilings], "r")
    assert len(cmds) == 3 and not any("--weathers clean" in c for c in cmds)  # no command of its own
    ran = set()
    for c in cmds:
        words = c.split()
        get = {words[i]: words[i + 1].split(",") for i in range(2, len(words) - 1, 2)}
        if not c.endswith(" --no-ceiling"):
            mine = {(sc, int(seed)) for sc in get["--scenes"] for seed in get["--seeds"]}
            assert mine <= ceilings, c
            ran |= mine
    assert ran == ceilings
    assert sum(c.endswith(" --no-ceiling") for c in cmds) == 1


def test_the_report_shows_the_clean_ceiling(store, tmp_path):
    """Its renders stand beside each setting's methods; the summary has it first and each row's gap to it."""
    root = tmp_path / "root"
    shutil.copytree(store, root)
    [ceiling] = [c for c in build_cells(["garden"], ["H"], ["3dgs"], ["tiny"], [0], "tiny", {"iterations": "6"},
                                        ceiling=True) if c.is_ceiling]
    [rec] = run_grid([ceiling], root, InlineExecutor(), CellOptions(lpips_net=None), progress=False,
                     log=lambda s: None).ran
    assert rec["status"] == "ok", rec.get("error")
    page = build_report(root, tmp_path / "report", ReportOptions(method_order=("nimbus", "3dgs")))
    parser = Page()
    parser.feed(page.read_text(encoding="utf-8"))
    rows = [r for r in parser.summary if r]
    assert [r[:2] for r in rows] == [["clean", "3DGS (clean views)"], ["H", "nimbus"], ["H", "3dgs"]]
    assert rows[0][-2:] == ["–", "–"]  # neither a degraded input nor a gap of its own
    records = {r["method"]: r for r in ResultsStore(root).records() if r["weather"] == "H"}
    for row in rows[1:]:
        assert row[-1] == f"{records[row[1]]['psnr'] - rec['psnr']:.2f}"
    html = page.read_text(encoding="utf-8")
    assert "<th>3DGS (clean views)</th>" in html and "haze (H)" in html and "(clean)" not in html
    for v in rec["per_view"]:
        assert f"{v['psnr']:.2f} dB" in html
    assert any(ceiling.cell_id in r for r in parser.refs) and all((page.parent / unquote(r)).is_file()
                                                                   for r in parser.refs if "://" not in r
                                                                   and not r.startswith(".."))
    assert "--no-ceiling" not in html  # the store has the ceiling a plain command runs


def test_evenly_spaced_keeps_both_ends():
    assert evenly_spaced(list("abcdefg"), 3) == ["a", "d", "g"]
    assert evenly_spaced(list("ab"), 5) == ["a", "b"]
    assert evenly_spaced(list("abc"), 1) == ["a"]


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_chromium() is None, reason="headless Chromium is not installed (apt-get install chromium)")
def test_the_page_renders_to_a_screenshot_that_is_not_blank(report, tmp_path):
    import cv2

    out, page, _ = report
    shot = tmp_path / "shot.png"
    subprocess.run([_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={shot}", "--window-size=1000,1400", page.resolve().as_uri()],
                   check=True, capture_output=True, timeout=120)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (1400, 1000)
    # Not blank: text and thumbnails make many distinct, non-white pixels.
    assert (img < 200).any(axis=2).mean() > 0.02
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 500


@pytest.mark.skipif(_chromium() is None, reason="headless Chromium is not installed (apt-get install chromium)")
def test_the_scripts_sort_toggle_the_differences_and_enlarge(report, tmp_path):
    out, page, _ = report
    probe = out / "probe.html"  # the page, clicked by a script of the test's, in the report folder (same paths)
    probe.write_text(page.read_text(encoding="utf-8").replace(
        "</body>", "<script>document.getElementById('diff').click();"
                   "document.querySelector('#summary th:nth-child(2)').click();"
                   "document.querySelector('a.zoom').click();</script></body>"), encoding="utf-8")
    try:
        dom = subprocess.run([_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom",
                              probe.resolve().as_uri()], check=True, capture_output=True, text=True, timeout=120).stdout
    finally:
        probe.unlink()
    parser = Page()
    parser.feed(dom)
    # Sorted by method name, ascending (the page lists nimbus first: --methods order).
    assert [r[1] for r in parser.summary if r] == ["3dgs", "nimbus"]
    diffs = re.findall(r'<img[^>]*\bsrc="([^"]+)"[^>]*\bdata-diff="([^"]+)"', dom)
    assert diffs and all(src == diff for src, diff in diffs)  # every thumbnail shows its difference
    assert re.search(r'<div id="lightbox" style="display: flex;"><img[^>]*src="[^"]+_diff\.jpg"', dom)


def test_the_templates_escape_what_they_show():
    from benchmark.tables.model import Block, Column, Row, Table
    from benchmark.tables.writer import to_html, to_text

    t = Table("t", "t", "T", (Column("v", "v<w", "v", 1, higher_is_better=True),), [""],
              [Block([Row("<script>alert(1)</script>", {("", "v"): 2.0}), Row("b&c", {("", "v"): 1.0})], name="H")],
              lead=("Method", "Weather"), notes=["a <i>note</i>"])
    html = to_html(t)
    assert "<script>" not in html and "<i>" not in html
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in html and "b&amp;c" in html and "v&lt;w" in html
    assert '<td data-v="2.0" class="best">2.0</td>' in html and '<td data-v="1.0">1.0</td>' in html
    # Text is not HTML: as it is, in columns (labels left, values right), the notes below.
    assert to_text(t).splitlines() == ["Weather  Method                     v<w",
                                       "H        <script>alert(1)</script>  2.0",
                                       "H        b&c                        1.0", "a <i>note</i>."]


def test_another_commands_csv_is_a_table_of_the_writer(tmp_path):
    from benchmark.tables.writer import from_csv, to_html

    path = tmp_path / "tradeoff.csv"
    path.write_text("knob,value,psnr,note\niterations,6,12.5,<b>\niterations,12,inf,\n")
    t = from_csv(path)
    assert [c.text for c in t.columns] == ["value", "psnr", "note"] and t.lead == ("knob",)
    html = to_html(t)
    assert "<th>knob</th><th>value</th><th>psnr</th><th>note</th>" in html  # no block column: no block has a name
    assert '<td data-v="12.5">12.5</td><td>&lt;b&gt;</td>' in html  # numbers sort by value, text by what it says
    assert '<td data-v="">inf</td>' in html  # not a finite number: sorted last
    empty = tmp_path / "stability.csv"
    empty.write_text("")
    assert "stability.csv is empty." in to_html(from_csv(empty))
