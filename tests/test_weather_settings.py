"""Weather tokens, seed derivation and config overrides of the synthesizer."""

import hashlib

import pytest

from nimbus.errors import NimbusError
from nimbus.config_set import apply_overrides, parse_set_args
from weather_synth.config import SynthConfig, protocol_config
from weather_synth.seeds import derive_seed, rng_for
from weather_synth.settings import ALL_SETTING_NAMES, parse_weather


def names(spec):
    return [s.name for s in parse_weather(spec)]


def test_tokens_are_case_insensitive_with_long_names_and_all():
    assert names("H,R,S,H+R,H+S,R+S,H+R+S") == list(ALL_SETTING_NAMES)
    assert names("all") == list(ALL_SETTING_NAMES)
    assert names("ALL") == list(ALL_SETTING_NAMES)
    assert names("haze+rain") == ["H+R"]
    assert names("rain+haze, s, Fog+Snow+Rain") == ["H+R", "S", "H+R+S"]
    # Duplicates (in any spelling) are written once, first order kept.
    assert names("R,rain,H,r") == ["R", "H"]


@pytest.mark.parametrize("spec, fragment", [
    ("H,drizzle", "unknown weather token 'drizzle'"),
    ("H+", "empty weather component"),
    ("H,,R", "empty weather component"),
    ("", "no weather given"),
    ("rain+r", "repeats a component"),
])
def test_bad_tokens_say_what_is_valid(spec, fragment):
    with pytest.raises(NimbusError) as e:
        parse_weather(spec)
    assert fragment in str(e.value)
    if "unknown" in fragment:
        assert "H|haze" in str(e.value) and "H+R+S" in str(e.value)


def test_setting_names_are_filesystem_safe():
    for s in parse_weather("all"):
        assert all(c.isalnum() or c == "+" for c in s.name)
        assert s.description.replace(" + ", "").isalpha()


def test_derived_seeds_are_sha256_of_the_names_and_independent():
    expected = int.from_bytes(hashlib.sha256("7\x1frain\x1f000.png".encode()).digest()[:8], "little")
    assert derive_seed(7, "rain", "000.png") == expected
    assert derive_seed(7, "rain", "000.png") != derive_seed(7, "rain", "001.png")
    assert derive_seed(7, "rain", "000.png") != derive_seed(7, "snow", "000.png")
    assert derive_seed(7, "rain", "000.png") != derive_seed(8, "rain", "000.png")
    assert rng_for(3, "x").random() == rng_for(3, "x").random()


def test_overrides_reach_nested_fields_and_refuse_unknown_keys():
    items = ["haze.fog_noise_amplitude=0.25", "rain.slices=3", "seed=4", "haze.airlight=[0.7,0.8,0.9]",
             "compose.linear=false"]
    cfg = apply_overrides(protocol_config("physical"), parse_set_args(items))
    assert cfg.haze.fog_noise_amplitude == 0.25 and cfg.rain.slices == 3 and cfg.seed == 4
    assert cfg.haze.airlight == (0.7, 0.8, 0.9) and cfg.compose.linear is False
    with pytest.raises(NimbusError, match="unknown setting 'haze.bogus'.*valid keys"):
        apply_overrides(cfg, parse_set_args(["haze.bogus=1"]))
    with pytest.raises(NimbusError, match="haze.visibility_scale=thick: must be a finite number > 0"):
        apply_overrides(cfg, parse_set_args(["haze.visibility_scale=thick"]))
    with pytest.raises(NimbusError, match="key=value"):
        apply_overrides(cfg, parse_set_args(["haze.beta"]))
    # Values are validated against the config's limits before they are set.
    with pytest.raises(NimbusError, match=r"haze.beta=-1: must be a number >= 0"):
        apply_overrides(cfg, parse_set_args(["haze.beta=-1"]))


def test_protocol_presets():
    one, phys = protocol_config("onerestore"), protocol_config("physical")
    assert (one.haze.mode, one.compose.order, one.compose.linear, one.depth_aware) == \
        ("onerestore", "onerestore", False, False)
    assert (phys.haze.mode, phys.compose.order, phys.compose.linear, phys.depth_aware) == \
        ("homogeneous", "physical", True, True)
    assert one.haze.beta_range == (1.0, 2.0) and one.haze.airlight_range == (0.6, 0.9)
    with pytest.raises(NimbusError, match="unknown protocol"):
        protocol_config("cinematic")
    with pytest.raises(NimbusError, match="seed"):
        SynthConfig(seed=-1)
