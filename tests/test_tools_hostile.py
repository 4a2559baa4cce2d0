"""``python -m tools.hostile``: the hostile-input tests run and tabulated by family (family, cases, clean, holes)."""

from __future__ import annotations

import pytest

from tools import hostile
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError

# Stand-in families: "alpha" ends cleanly, "beta" has a hole (a failing case) and a skipped one.
FAMILIES = {
    "alpha": "def test_one():\n    assert True\n\ndef test_two():\n    assert 1 + 1 == 2\n",
    "beta": ("import pytest\n\ndef test_clean():\n    pass\n\ndef test_leaks():\n    assert False, 'wrote outside'\n\n"
             "@pytest.mark.skip(reason='no gpu')\ndef test_gpu():\n    pass\n"),
}


@pytest.fixture
def fake_tests(tmp_path):
    tests = tmp_path / "tests"
    tests.mkdir()
    for name, text in FAMILIES.items():
        (tests / f"test_hostile_{name}.py").write_text(text)
    (tests / "test_other.py").write_text("def test_not_a_family():\n    assert False\n")
    return tests


def test_every_hostile_test_file_is_a_family():
    assert hostile.families() == ["bench", "config", "data", "synth", "train"]


def test_families_are_run_and_tallied_with_their_holes_named(fake_tests):
    alpha, beta = hostile.run_families(["alpha", "beta"], tests=fake_tests)
    assert (alpha.cases, alpha.clean, alpha.holes, alpha.skipped) == (2, 2, [], 0)
    assert (beta.cases, beta.clean, beta.holes, beta.skipped) == (2, 1, ["test_hostile_beta.py::test_leaks"], 1)
    md = hostile.to_markdown(hostile.table([alpha, beta]))
    assert "| family | cases | ended cleanly | holes |" in md
    assert "| alpha | 2 | 2 | 0 |" in md and "| beta | 2 | 1 | 1 |" in md and "| all | 4 | 3 | 1 |" in md
    assert "Hole: test_hostile_beta.py::test_leaks." in md and "1 case(s) skipped" in md


def test_unknown_family_is_one_clear_error(fake_tests, capsys):
    assert hostile.pick("alpha", fake_tests) == ["alpha"]
    with pytest.raises(NimbusError, match="unknown hostile family 'gamma'; choose from alpha, beta"):
        hostile.pick("alpha,gamma", fake_tests)
    assert run_cli(hostile.main, ["--families", "nope"]) == 2
    assert capsys.readouterr().err.startswith("error: unknown hostile family 'nope'")
