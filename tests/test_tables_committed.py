"""The committed table folders that hold their records regenerate from them byte for byte.

``tables/small_fast_6methods`` (issue 17's grid), ``tables/cuda_check_small_fast`` (its CUDA check),
``tables/default_tiny`` (the default grid) and ``tables/main_compact`` (the README main job) keep their
``results.jsonl``, and so does ``tables/validation_tiny``, whose
README's summaries are checked against its tool; the commands their READMEs give must write exactly the committed files, so a change
to a table layout that moves a committed figure or sentence shows here, not in a reader's diff.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from benchmark.cli import TOOL
from nimbus.cli_util import run_cli

TABLES = Path(__file__).resolve().parents[1] / "tables"
METHODS = "nimbus,nimbus-paper,3dgs,restore-3dgs,robust-3dgs,medium-3dgs"  # the READMEs' --methods


def same_files(out: Path, committed: Path) -> None:
    written = sorted(p.name for p in out.iterdir())
    # README.md and the records (results.jsonl, and any other store a README cites, e.g. a cost run's) are inputs
    assert written == sorted(p.name for p in committed.iterdir() if p.name != "README.md" and p.suffix != ".jsonl")
    for name in written:
        assert (out / name).read_bytes() == (committed / name).read_bytes(), name


@pytest.fixture
def issue17(tmp_path):
    root = tmp_path / "bench17"
    root.mkdir()
    shutil.copyfile(TABLES / "small_fast_6methods" / "results.jsonl", root / "results.jsonl")
    return root


def test_issue17_tables_regenerate(issue17, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(TOOL.run, ["tables", "--root", str(issue17), "--out", str(out), "--methods", METHODS]) == 0
    capsys.readouterr()
    same_files(out, TABLES / "small_fast_6methods")


def test_cuda_check_regenerates(issue17, tmp_path, capsys):
    cuda = tmp_path / "bench17_cuda"
    cuda.mkdir()
    shutil.copyfile(TABLES / "cuda_check_small_fast" / "results.jsonl", cuda / "results.jsonl")
    out = tmp_path / "out"
    assert run_cli(TOOL.run, ["compare", "--root", str(issue17), "--against", str(cuda), "--names", "cpu,cuda",
                              "--methods", METHODS, "--out", str(out)]) == 0
    capsys.readouterr()
    same_files(out, TABLES / "cuda_check_small_fast")


def _tables_regenerate(folder: str, tmp_path, capsys, *options: str) -> None:
    """``nimbus-bench tables`` on a copy of ``tables/FOLDER/results.jsonl`` writes exactly the committed files."""
    root = tmp_path / folder
    root.mkdir()
    shutil.copyfile(TABLES / folder / "results.jsonl", root / "results.jsonl")
    out = tmp_path / "out"
    assert run_cli(TOOL.run, ["tables", "--root", str(root), "--out", str(out), *options]) == 0
    capsys.readouterr()
    same_files(out, TABLES / folder)


def test_default_tiny_tables_regenerate(tmp_path, capsys):
    """The default grid's tables (three scenes, seven settings, three seeds, the ceiling)."""
    _tables_regenerate("default_tiny", tmp_path, capsys)


def test_main_compact_tables_regenerate(tmp_path, capsys):
    """The README main job's tables (street at compact size, H, R and S, the ceiling)."""
    _tables_regenerate("main_compact", tmp_path, capsys)


def test_street_small_h_tables_regenerate(tmp_path, capsys):
    """NimbusGS with and without the dehazed-view prior against restore-3dgs on the small street, H (issue 34)."""
    _tables_regenerate("street_small_H", tmp_path, capsys, "--methods", "nimbus,restore-3dgs")


def test_small_hazy_tables_regenerate(tmp_path, capsys):
    """NimbusGS against restore-3dgs on the small scenes under the four hazy settings, at one commit (issue 34)."""
    _tables_regenerate("small_hazy", tmp_path, capsys, "--methods", "nimbus,restore-3dgs")


@pytest.mark.parametrize("folder, methods", [
    ("small_grid_seed0", "nimbus,restore-3dgs,3dgs,robust-3dgs,medium-3dgs"),  # every method, seed 0, the newest records
    ("small_haze_free", "nimbus,3dgs,robust-3dgs"),  # R, S and R+S on the three small scenes, at one commit
    ("small_hazy_particle_cut", "nimbus,restore-3dgs"),  # restore-3dgs again with its particle cut of 2026-12-01
    ("small_street_S_seeds", "nimbus,3dgs,robust-3dgs"),  # the smallest haze-free margin, three training seeds
    ("small_paper_H", "nimbus-paper,nimbus-paper[lambda_dehaze=1],3dgs"),  # nimbus-paper at small size, under H
    ("small_paper_R", "nimbus-paper,nimbus-paper[residual_tophat=0.03],3dgs"),  # and under R
    ("small_paper_more", "nimbus-paper,nimbus-paper[lambda_dehaze=1],nimbus-paper[components=auto,consistency_neighbours=4,"
                         "residual_outlier_sigmas=3,residual_tophat=0.03],3dgs,nimbus,restore-3dgs"),  # the other five settings
    ("small_paper_tabletop", "nimbus-paper,nimbus-paper[lambda_dehaze=1],nimbus-paper[components=auto,"
                             "consistency_neighbours=4,residual_outlier_sigmas=3,residual_tophat=0.03],3dgs,nimbus,"
                             "restore-3dgs"),  # the same on the third scene
    ("small_physical", "nimbus,restore-3dgs,3dgs"),  # one-medium (physical) haze, garden and street, H and H+R+S
])
def test_issue34_small_tables_regenerate(folder, methods, tmp_path, capsys):
    """Issue 34's small-scene folders of 2026-11-30, each with the README's --methods."""
    _tables_regenerate(folder, tmp_path, capsys, "--methods", methods)


def test_tables_name_a_methods_entry_that_orders_no_row(tmp_path, capsys):
    """A misspelt --methods entry (here an override set the store does not hold) still writes the tables, and says so."""
    root = tmp_path / "r"
    root.mkdir()
    shutil.copyfile(TABLES / "small_paper_R" / "results.jsonl", root / "results.jsonl")
    args = ["tables", "--root", str(root), "--out", str(tmp_path / "out"), "--methods"]
    assert run_cli(TOOL.run, [*args, "nimbus-paper[residual_tophat=0.3],3dgs"]) == 0
    err = capsys.readouterr().err
    assert "no method named nimbus-paper[residual_tophat=0.3];" in err and "nimbus-paper[residual_tophat=0.03]" in err
    assert (tmp_path / "out" / "weather_R.md").exists()
    assert run_cli(TOOL.run, [*args, "nimbus-paper[residual_tophat=0.03],3dgs"]) == 0
    assert "--methods" not in capsys.readouterr().err
    # a label of several overrides holds commas of its own: the list splits only outside brackets
    many = "nimbus-paper[consistency_neighbours=4,residual_outlier_sigmas=3,residual_tophat=0.03]"
    assert run_cli(TOOL.run, [*args, f"3dgs,{many}"]) == 0
    assert "--methods" not in capsys.readouterr().err
    rows = [line.split(" | ")[0].lstrip("| ") for line in (tmp_path / "out" / "weather_R.md").read_text().splitlines()
            if "trained on R" in line]
    assert rows[:2] == ["3dgs", many]


def test_split_method_labels():
    from benchmark.store import split_method_labels

    assert split_method_labels(" a[x=1,y=2] , b,,c[z=3]") == ["a[x=1,y=2]", "b", "c[z=3]"]
    assert split_method_labels("nimbus") == ["nimbus"] and split_method_labels(" , ") == []


def test_validation_tiny_summaries_regenerate():
    """Every ``tools.validation_cells --summary`` block in tables/validation_tiny/README.md is followed by its output."""
    from tools.validation_cells import summary

    readme = (TABLES / "validation_tiny" / "README.md").read_text()
    fences = list(re.finditer(r"```[a-z]*\n(.*?)```\n", readme, re.S))
    checked = 0
    for fence, following in zip(fences, [*fences[1:], None]):
        after = readme[fence.end():following.start() if following else len(readme)]
        lines = fence.group(1).splitlines()
        if not all(line.startswith("python -m tools.validation_cells --summary") for line in lines):
            continue  # a recipe, not a summary and its output
        for line in lines:
            args = line.split()
            records = Path(__file__).resolve().parents[1] / args[args.index("--summary") + 1]
            assert summary(records, args[args.index("--tags") + 1].split(",")) in after, line
            checked += 1
    assert checked >= 4


def test_validation_summary_refuses_tags_without_a_common_cell(tmp_path, capsys):
    from tools.validation_cells import main

    records = tmp_path / "records.jsonl"
    records.write_text("".join(json.dumps({"tag": t, "folder": f"VAL/seed-1/data/{c}/H", "psnr": 20.0, "ssim": 0.5})
                               + "\n" for t, c in (("a", "garden-tiny"), ("b", "street-tiny"))))
    assert main(["--summary", str(records), "--tags", "a,b"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no cell has a record of every tag") and "a: 1 cell(s); b: 1 cell(s)" in err
    assert main(["--summary", str(records), "--tags", "a"]) == 0
    assert "| seed-1 garden-tiny H | 20.00 / 0.500 |" in capsys.readouterr().out


@pytest.mark.parametrize("folder", ["small_H", "small_H_before_sky", "small_HRS", "small_HS", "small_HR"])
def test_small_h_tables_regenerate(folder, tmp_path, capsys):
    """NimbusGS against restore-3dgs on the small scenes under H (with and before the dehaze's sky tolerance) and
    under H+R+S and H+S (issue 34)."""
    _tables_regenerate(folder, tmp_path, capsys, "--methods", "nimbus,restore-3dgs")
