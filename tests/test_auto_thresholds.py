"""The rule ``python -m tools.auto_thresholds`` derives ``auto``'s thresholds by, on made-up cells (no training)."""

import numpy as np
import pytest

from tools.auto_thresholds import (VARIANTS, Cell, choose, derive_haze, derive_particles, margin, shortfall,
                                       variant_overrides)
from nimbus.config_set import apply_overrides
from nimbus.methods.nimbusgs.auto import haze_present, particle_thresholds
from nimbus.methods.nimbusgs.config import preset


def cell(name, plm_gain, asym, energy, dark=0.05, corr=0.0, csm_gain=-1.0):
    """A cell whose PLM gains ``plm_gain`` dB (CSM on or off) and CSM ``csm_gain``; evidence alike either way."""
    base = 20.0
    psnr = {"none": base, "plm": base + plm_gain, "csm": base + csm_gain, "csm+plm": base + csm_gain + plm_gain}
    return Cell("scene-tiny", name, psnr, dark, corr, {True: (asym, energy), False: (asym, energy)})


def test_particle_rule_declares_every_needed_cell_and_gives_away_the_fewest_db():
    # R and S need PLM (>= 0.3 dB); "a" gains 0.1 dB, below the bar but still worth taking; "b" loses 0.5 dB.
    cells = [cell("R", 2.0, 0.30, 0.0010), cell("S", 0.4, 0.22, 0.0008), cell("a", 0.1, 0.25, 0.0002),
             cell("b", -0.5, 0.10, 0.0020), cell("c", 0.0, 0.35, 0.0030)]
    hazy = np.zeros(len(cells), bool)
    choice, declared = derive_particles(cells, hazy, False, (0.5, 0.0005))
    assert not choice.kept and declared.tolist() == [True, True, True, False, True]
    assert choice.shortfall == 0.0 and choice.false == 2
    # Half-way between b's asymmetry and the lowest declared one; energy does not constrain (below every value).
    a, e = choice.thresholds
    assert a == 0.16 and e == 0.0
    # The count-the-false-declarations rule would have left "a" out (threshold 0.16 / 0.0005): 0.1 dB given away.
    assert shortfall(np.array([2.0, 0.4, 0.1, -0.5, 0.0]), np.array([True, True, False, False, True])) == \
        pytest.approx(0.1)


def test_particle_rule_never_misses_a_needed_cell_even_at_a_cost():
    # Declaring R (needs PLM) forces declaring "b" too (higher evidence, loses 1 dB): the rule pays it.
    cells = [cell("R", 0.35, 0.20, 0.001), cell("b", -1.0, 0.30, 0.001), cell("c", -1.0, 0.05, 0.001)]
    choice, declared = derive_particles(cells, np.zeros(3, bool), False, (0.5, 0.0))
    assert declared.tolist() == [True, True, False]
    assert choice.shortfall == pytest.approx(1.0) and choice.false == 1


def test_of_equally_good_rules_the_widest_margin_wins_and_a_current_rule_on_the_edge_is_replaced():
    cells = [cell("R", 1.0, 0.50, 0.001), cell("b", -0.5, 0.10, 0.001), cell("c", 0.0, 0.49, 0.001)]
    hazy = np.zeros(3, bool)
    # "c" (no gain either way) may go either way at no cost: half-way 0.10 .. 0.49 (0.295, rounded to 0.29) has
    # the wider margin than half-way 0.49 .. 0.50.
    choice, declared = derive_particles(cells, hazy, False, (0.4999, 0.0))
    assert declared.tolist() == [True, False, True] and choice.thresholds[0] == 0.29
    assert not choice.kept and choice.margin > 0.5
    # The current thresholds, as good and well inside the same gap, are kept.
    choice, _ = derive_particles(cells, hazy, False, (0.25, 0.0))
    assert choice.kept and choice.thresholds == (0.25, 0.0)


def test_margin_is_how_far_thresholds_move_before_a_decision_changes():
    values = np.array([0.2, 0.6])

    def declare(t):
        return values >= t[0]

    assert margin(declare, (0.5,), np.array([1.0])) == pytest.approx(0.1, abs=1e-6)
    assert margin(declare, (0.5,), np.array([0.5])) == pytest.approx(0.2, abs=1e-6)  # in units of the spread
    assert margin(declare, (0.6,), np.array([1.0])) == pytest.approx(0.0, abs=1e-6)  # on a value: no margin


def test_particle_rule_uses_only_its_group():
    cells = [cell("H+R", 1.0, 0.12, 0.0003), cell("R", 1.0, 0.30, 0.0010), cell("b", -0.2, 0.20, 0.0009)]
    hazy = np.array([True, False, False])
    choice, declared = derive_particles(cells, hazy, True, (0.35, 0.0005))
    (a, e) = choice.thresholds
    assert declared.tolist() == [True] and a <= 0.12 and e <= 0.0003
    choice, declared = derive_particles(cells, hazy, False, (0.35, 0.0005))
    assert declared.tolist() == [True, False] and choice.false == 0 and 0.20 < choice.thresholds[0] <= 0.30


def test_haze_rule_keeps_current_thresholds_when_they_are_as_good():
    cells = [cell("H", 0.0, 0, 0, dark=0.30, csm_gain=3.0), cell("R", 0.0, 0, 0, dark=0.05, csm_gain=-2.0),
             cell("thin", 0.0, 0, 0, dark=0.12, corr=0.8, csm_gain=0.5)]
    choice = derive_haze(cells, (0.2, 0.5))
    assert choice.kept and choice.thresholds == (0.2, 0.5) and choice.false == 0 and choice.shortfall == 0
    choice = derive_haze(cells, (0.4, 0.5))  # misses H and the thin veil
    assert not choice.kept and choice.false == 0
    d, c = choice.thresholds
    assert [haze_present(x.dark_median, x.dark_depth_corr, d, c) for x in cells] == [True, False, True]


def test_choose_refuses_rules_that_miss_a_needed_cell():
    gains = np.array([1.0, -0.2, -0.3])
    values = np.array([0.1, 0.5, 0.9])
    choice = choose(gains, lambda t: values >= t[0], [(0.7,), (0.3,), (0.0,)], (0.7,), np.array([1.0]))
    assert choice.thresholds == (0.0,) and choice.false == 2 and not choice.kept
    assert choice.shortfall == pytest.approx(0.5)


def test_variants_force_auto_one_way_whatever_the_evidence():
    cfg = preset("tiny")
    for csm, plm in VARIANTS.values():
        c = apply_overrides(cfg, variant_overrides(csm, plm))
        for dark, corr in ((0.0, 0.0), (0.99, 0.99)):
            assert haze_present(dark, corr, c.auto_dark_threshold, c.auto_depth_corr) == csm
        for hazy in (False, True):
            a, e = particle_thresholds(c, hazy)
            for asym, energy in ((-0.99, 0.0), (0.99, 1.0)):
                assert (asym >= a and energy >= e) == plm


@pytest.mark.parametrize("argv", [["--sizes", "huge"], ["--report", "--sizes", "huge"]])
def test_an_unknown_size_is_one_line_and_writes_nothing(argv, tmp_path, monkeypatch, capsys):
    from tools import auto_thresholds, restore_thresholds
    from nimbus.cli_util import run_cli

    monkeypatch.chdir(tmp_path)
    for main in (auto_thresholds.main, restore_thresholds.main):
        if main is restore_thresholds.main and "--report" in argv:
            continue
        assert run_cli(main, argv) == 2
        assert "unknown scene size 'huge'" in capsys.readouterr().err
        assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("seeds", ["0", "1,0", "-3", "2,2"])
def test_the_benchmarks_own_scene_seed_is_refused_for_validation(seeds, tmp_path, monkeypatch, capsys):
    from tools import auto_thresholds
    from nimbus.cli_util import run_cli

    monkeypatch.chdir(tmp_path)
    assert run_cli(auto_thresholds.main, ["--scene-seeds", seeds]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--scene-seeds {seeds!r}: give distinct integers >= 1" in err[0]
    assert not list(tmp_path.iterdir())


def test_a_root_made_with_another_scene_seed_is_refused_before_anything_is_written(tmp_path, capsys):
    from tools import auto_thresholds
    from nimbus.cli_util import run_cli

    made = tmp_path / "val" / "seed-2" / "scenes" / "garden-tiny"  # a seed-1 scene where seed 2's belong
    made.mkdir(parents=True)
    (made / "manifest.json").write_text('{"seed": 1}')
    before = sorted(tmp_path.rglob("*"))
    assert run_cli(auto_thresholds.main, ["--root", str(tmp_path / "val"), "--scene-seeds", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "was made with seed 1, not 2" in err[0]
    assert sorted(tmp_path.rglob("*")) == before


def test_checks_report_each_default_against_its_runs_and_skip_haze_only_checks_on_clear_cells(capsys):
    from tools.auto_thresholds import CHECKS, HAZE_ONLY_CHECKS, report_checks

    assert HAZE_ONLY_CHECKS <= set(CHECKS)
    cells = [cell("H", 0.0, 0.1, 0.0, csm_gain=2.0), cell("R", 1.0, 0.3, 0.001)]
    recs = {}
    for name in CHECKS:  # each check costs 0.5 dB on the hazy cell (its base: csm+plm) and gains 0.25 on the other
        recs[("scene-tiny", "H", name)] = {"psnr": cells[0].psnr["csm+plm"] - 0.5, "components": ["csm", "plm"]}
        if name not in HAZE_ONLY_CHECKS:
            recs[("scene-tiny", "R", name)] = {"psnr": cells[1].psnr["plm"] + 0.25, "components": ["plm"]}
    base = {("scene-tiny", "H", "csm+plm"): {"psnr": cells[0].psnr["csm+plm"]},
            ("scene-tiny", "R", "plm"): {"psnr": cells[1].psnr["plm"]}}
    report_checks(cells, recs, base)
    lines = {line.split(":")[0]: line for line in capsys.readouterr().out.splitlines() if line.startswith("default")}
    for name in CHECKS:
        line = lines[f"default minus {name}"]
        if name in HAZE_ONLY_CHECKS:
            assert "mean +0.500 dB" in line and "1 of 1 cells" in line
        else:
            assert "mean +0.125 dB" in line and "1 of 2 cells" in line


def test_gains_and_evidence_are_means_over_the_training_seeds(tmp_path):
    from tools.auto_thresholds import gather, seed_name, split_seed

    assert seed_name("csm+plm", 0) == "csm+plm" and seed_name("csm+plm", 1) == "csm+plm@s1"
    assert split_seed("csm+plm@s1") == ("csm+plm", 1) and split_seed("none") == ("none", 0)
    haze = {"dark_median": 0.05, "dark_depth_corr": 0.0}

    def rec(psnr, asym, energy):
        return {"psnr": psnr, "haze": haze, "particles": {"asymmetry": asym, "energy": energy}}

    recs = {("d", "R", "plm"): rec(20.5, 0.2, 0.001), ("d", "R", "none"): rec(20.0, 0.2, 0.001),
            ("d", "R", "plm@s1"): rec(19.9, 0.4, 0.003), ("d", "R", "none@s1"): rec(20.0, 0.4, 0.003),
            ("d", "R", "csm"): rec(15.0, 0.3, 0.002), ("d", "R", "csm+plm"): rec(15.2, 0.3, 0.002)}
    [c] = gather([("d", "R", tmp_path)], recs, [0, 1])
    # seed 0 alone: PLM gains 0.5 dB (needed); with seed 1 (-0.1 dB) the mean gain is 0.2 dB
    assert c.plm_gain(False) == pytest.approx(0.2) and c.particles[False] == pytest.approx((0.3, 0.002))
    assert c.complete and c.psnr["csm"] == 15.0
    [one] = gather([("d", "R", tmp_path)], recs, [0])
    assert one.plm_gain(False) == pytest.approx(0.5)


@pytest.mark.parametrize("text", ["", "a", "1,1", "-1", "0,,x"])
def test_bad_training_seeds_are_one_clear_error(text):
    from tools.auto_thresholds import parse_seeds
    from nimbus.errors import NimbusError

    with pytest.raises(NimbusError, match="--seeds"):
        parse_seeds(text)


def test_cells_of_each_scene_seed_are_apart(tmp_path, monkeypatch):
    from tools import auto_thresholds

    def fake_prepare(root, sizes, seed):
        data = root / "data" / "garden-tiny"
        (data / "H").mkdir(parents=True)
        (data / "H" / "manifest.json").write_text("{}")
        return [data]

    monkeypatch.setattr(auto_thresholds, "prepare", fake_prepare)
    cells = auto_thresholds.cell_folders(tmp_path, ["tiny"], (1, 2))
    assert [(d, s) for d, s, _ in cells] == [("garden-tiny@1", "clean"), ("garden-tiny@1", "H"),
                                             ("garden-tiny@2", "clean"), ("garden-tiny@2", "H")]
    assert cells[0][2] == tmp_path / "seed-1" / "scenes" / "garden-tiny"
    assert cells[3][2] == tmp_path / "seed-2" / "data" / "garden-tiny" / "H"


def _store(root, seed=1, pairs=(("H", 19.1, 19.3, ["csm", "plm", "ggs"], 0.03),
                                ("H+R", 17.5, 16.8, ["csm", "plm", "ggs"], 0.40))):
    """A benchmark store with a nimbus / nimbus-no-plm pair per setting, as ``nimbus-bench run`` writes one."""
    import json

    (root / "scenes" / "garden-small").mkdir(parents=True)
    (root / "scenes" / "garden-small" / "manifest.json").write_text(json.dumps({"seed": seed}))
    lines = []
    for setting, on, off, components, asym in pairs:
        for method, psnr in (("nimbus", on), ("nimbus-no-plm", off)):
            cid = f"garden-small_{setting}_{method}_fast_s0"
            lines.append({"cell_id": cid, "status": "ok", "scene": "garden", "size": "small", "weather": setting,
                          "preset": "fast", "seed": 0, "method": method, "psnr": psnr, "overrides": {},
                          "components": components if method == "nimbus" else ["csm", "ggs"]})
            (root / "runs" / cid).mkdir(parents=True)
            (root / "runs" / cid / "results.json").write_text(json.dumps({"nimbus": {
                "haze_evidence": {"dark_median": 0.4, "dark_depth_corr": 0.6},
                "particle_evidence": {"asymmetry": asym, "energy": 0.001}}}))
    (root / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    return root


def test_a_stores_pairs_are_hazy_cells_with_plm_on_and_off(tmp_path):
    from tools.auto_thresholds import store_cells

    cells = store_cells(_store(tmp_path))
    assert [(c.setting, c.psnr, c.particles[True]) for c in cells] == [
        ("H", {"csm+plm": 19.1, "csm": 19.3}, (0.03, 0.001)), ("H+R", {"csm+plm": 17.5, "csm": 16.8}, (0.40, 0.001))]
    assert [round(c.plm_gain(True), 2) for c in cells] == [-0.2, 0.7]
    # the derivation then declares the H+R cell (a gain >= 0.3 dB) and, at the least cost, not the H one
    choice, declared = derive_particles(cells, np.array([True, True]), True, (-1.0, 0.0))
    assert declared.tolist() == [False, True] and choice.shortfall == 0.0


def test_a_cell_auto_left_haze_free_is_not_a_hazy_pair(tmp_path):
    from tools.auto_thresholds import store_cells

    cells = store_cells(_store(tmp_path, pairs=(("H", 19.1, 19.3, ["csm", "plm", "ggs"], 0.03),
                                                ("R", 25.0, 24.0, ["plm"], 0.5))))
    assert [c.setting for c in cells] == ["H"]


@pytest.mark.parametrize("seed, pairs, message", [
    (0, None, "seed 0"),
    (1, (), "no hazy cell"),
])
def test_a_store_of_the_benchmarks_own_scenes_or_without_pairs_is_refused(seed, pairs, message, tmp_path, capsys):
    from tools.auto_thresholds import main
    from nimbus.cli_util import run_cli

    root = _store(tmp_path, seed=seed) if pairs is None else _store(tmp_path, seed=seed, pairs=pairs)
    assert run_cli(main, ["--store", str(root)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_particle_share_is_the_cut_where_the_step_gains_most():
    from tools.restore_thresholds import best_share, share_gains

    rows = [{"white_share": s, "gain": g} for s, g in ((0.5, -1.0), (0.8, -2.0), (0.97, 1.0), (1.0, 0.5))]
    gains = share_gains(rows, cuts=(0.7, 0.9, 0.98))
    # A view below the cut gains nothing; the mean is over every view.
    assert gains == [(0.7, pytest.approx(-0.125)), (0.9, pytest.approx(0.375)), (0.98, pytest.approx(0.125)),
                     (float("inf"), 0.0)]
    assert best_share(gains) == 0.9
    # Where the step never gains, the highest cut wins: never run it.
    assert best_share(share_gains(rows[:2], cuts=(0.4, 0.9))) == float("inf")


def test_particle_gain_rows_score_the_step_against_the_clean_view(tmp_path):
    import cv2

    from tools.restore_thresholds import particle_gain_rows
    from test_restore_3dgs import _smooth_texture, _streaks

    clean = _smooth_texture()
    setting = tmp_path / "scene-tiny" / "R"
    for folder, img in (("clean", clean), ("images", _streaks(clean, n=120))):
        (setting / folder).mkdir(parents=True)
        cv2.imwrite(str(setting / folder / "000.png"), np.rint(img[..., ::-1] * 255).astype(np.uint8))
    (setting / "train_list.txt").write_text("000.png\n")
    (setting / "manifest.json").write_text("{}")
    (row,) = particle_gain_rows([tmp_path / "scene-tiny"])
    assert row["setting"] == "R" and row["white_share"] > 1.0
    assert row["gain"] > 3.0  # the streaks are removed: far closer to the clean view
