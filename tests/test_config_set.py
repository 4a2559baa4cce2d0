"""One ``--set`` grammar for every tool (nimbus/config_set.py) and one JSON policy (nimbus/utils/jsonable.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from nimbus.config_set import apply_overrides, parse_set_args
from nimbus.errors import NimbusError
from nimbus.methods.nimbusgs.config import PRESETS as NIMBUS_PRESETS
from nimbus.train.config import PRESETS as GS_PRESETS
from nimbus.utils.jsonable import jsonable
from weather_synth.config import protocol_config


@pytest.mark.parametrize("text", ["1,1,1", "[1, 1, 1]", "(1,1,1)", "1.0, 1.0, 1.0"])
def test_tuples_take_commas_with_or_without_brackets_in_every_tool(text):
    assert apply_overrides(GS_PRESETS["tiny"], {"background": text}).background == (1.0, 1.0, 1.0)
    assert apply_overrides(protocol_config(), {"haze.airlight": text}).haze.airlight == (1.0, 1.0, 1.0)


@pytest.mark.parametrize("text, value", [("true", True), ("1", True), ("on", True), ("Yes", True),
                                         ("false", False), ("0", False), ("off", False), ("NO", False)])
def test_booleans_read_the_same_in_every_tool(text, value):
    assert apply_overrides(GS_PRESETS["tiny"], {"random_background": text}).random_background is value
    assert apply_overrides(protocol_config(), {"compose.linear": text}).compose.linear is value


def test_values_are_parsed_by_the_field_type():
    cfg = apply_overrides(protocol_config(), {"haze.mode": '"homogeneous"', "haze.beta": "2", "rain.slices": "3.0",
                                              "haze.max_distance": "none", "seed": "12345678901"})
    assert cfg.haze.mode == "homogeneous" and cfg.haze.beta == 2.0 and isinstance(cfg.haze.beta, float)
    assert cfg.rain.slices == 3 and isinstance(cfg.rain.slices, int) and cfg.haze.max_distance is None
    assert cfg.seed == 12345678901  # exact, not through a float
    gs = apply_overrides(GS_PRESETS["tiny"], {"backend": '"torch"', "lr_opacity": "1e-2", "max_gaussians": "2e4"})
    assert (gs.backend, gs.lr_opacity, gs.max_gaussians) == ("torch", 0.01, 20_000)
    assert apply_overrides(gs, {}) is gs


def test_key_errors_name_the_valid_keys():
    with pytest.raises(NimbusError, match=r"unknown setting 'lr_opactiy'; did you mean lr_opacity.*valid keys here:"):
        apply_overrides(GS_PRESETS["tiny"], {"lr_opactiy": "0.1"})
    with pytest.raises(NimbusError, match=r"unknown setting 'hazy.beta'; did you mean haze\?"):
        apply_overrides(protocol_config(), {"hazy.beta": "1"})
    with pytest.raises(NimbusError, match="'haze' is a group of settings; set one of its keys, e.g. haze.<key>"):
        apply_overrides(protocol_config(), {"haze": "1"})
    with pytest.raises(NimbusError, match="'seed.x': seed has no sub-settings"):
        apply_overrides(protocol_config(), {"seed.x": "1"})
    with pytest.raises(NimbusError, match="'rain.layers' is a list of layer specs"):
        apply_overrides(protocol_config(), {"rain.layers": "1"})
    with pytest.raises(NimbusError, match="--set expects key=value, got 'seed'"):
        parse_set_args(["seed"])
    assert parse_set_args(["a = 1", "b=x=y", "a=2"]) == {"a": "2", "b": "x=y"}


def test_overrides_apply_together():
    # m_init < iterations holds only for the pair: each alone would fail against the preset's value.
    nimbus = apply_overrides(NIMBUS_PRESETS["tiny"], {"iterations": "30", "m_init": "20"})
    assert (nimbus.iterations, nimbus.m_init) == (30, 20)
    # iterations alone stretches the schedule; with a schedule field given, nothing is stretched
    tiny = GS_PRESETS["tiny"]
    assert apply_overrides(tiny, {"iterations": "600"}).densify_until == 2 * tiny.densify_until
    both = apply_overrides(tiny, {"iterations": "600", "densify_from": "10"})
    assert (both.densify_from, both.densify_until) == (10, tiny.densify_until)
    synth = apply_overrides(protocol_config(), {"haze.beta": "1", "haze.beta_range": "0,3", "rain.amount": "2"})
    assert (synth.haze.beta, synth.haze.beta_range, synth.rain.amount) == (1.0, (0.0, 3.0), 2.0)


def test_jsonable_writes_strict_json_with_an_explicit_nonfinite_policy():
    obj = {1: (np.float32(0.5), np.int64(3), np.bool_(True)), "a": np.array([1.0, np.inf]), "p": Path("x/y"),
           "v": [math.inf, -math.inf, math.nan, 2.0]}
    measured = jsonable(obj)
    assert measured == {"1": [0.5, 3, True], "a": [1.0, None], "p": "x/y", "v": [None, None, None, 2.0]}
    recorded = jsonable(obj, nonfinite="text")
    assert recorded["a"] == [1.0, "inf"] and recorded["v"] == ["inf", "-inf", "nan", 2.0]
    for doc in (measured, recorded):
        json.dumps(doc, allow_nan=False)  # strict JSON: raises on any inf / NaN left
    assert [float(v) for v in recorded["v"][:2]] == [math.inf, -math.inf]  # the text reads back
