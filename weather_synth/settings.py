"""Weather settings: which degradations a benchmark split combines, and their names.

A setting is a non-empty set of components: ``H`` (haze), ``R`` (rain), ``S``
(snow).  The paper's seven settings are H, R, S, H+R, H+S, R+S, H+R+S.

Names
-----
A setting's canonical name lists its components in the order H, R, S joined by
``+`` (``"H+R+S"``); the same string names its output folder.  ``+`` is legal in
file names on Linux, macOS and Windows and needs no shell quoting, and the names
match the paper's tables.

Parsing (:func:`parse_weather`)
-------------------------------
A comma-separated list of settings; each setting is components joined by ``+``.
Components are case-insensitive and accept long names: ``h``/``haze``/``fog``,
``r``/``rain``, ``s``/``snow``.  ``all`` expands to the seven settings.  So
``"H,R,haze+rain"`` and ``"h, r, H+R"`` name the same three settings.
"""

from __future__ import annotations

from dataclasses import dataclass

from nimbus.errors import NimbusError

COMPONENTS = ("H", "R", "S")
COMPONENT_NAMES = {"H": "haze", "R": "rain", "S": "snow"}
_ALIASES = {"h": "H", "haze": "H", "fog": "H", "r": "R", "rain": "R", "s": "S", "snow": "S"}
ALL_SETTING_NAMES = ("H", "R", "S", "H+R", "H+S", "R+S", "H+R+S")


@dataclass(frozen=True)
class WeatherSetting:
    """One combination of degradations.

    Attributes
    ----------
    components : frozenset of str
        Subset of ``{"H", "R", "S"}``, non-empty.
    """

    components: frozenset[str]

    def __post_init__(self) -> None:
        comps = frozenset(self.components)
        if not comps or not comps <= set(COMPONENTS):
            raise NimbusError(f"a weather setting needs components among {COMPONENTS}, got {sorted(comps)}")
        object.__setattr__(self, "components", comps)

    @property
    def name(self) -> str:
        """Canonical name and folder name, e.g. ``"H+R"``."""
        return "+".join(c for c in COMPONENTS if c in self.components)

    @property
    def haze(self) -> bool:
        return "H" in self.components

    @property
    def rain(self) -> bool:
        return "R" in self.components

    @property
    def snow(self) -> bool:
        return "S" in self.components

    @property
    def description(self) -> str:
        """Long form, e.g. ``"haze + rain"``."""
        return " + ".join(COMPONENT_NAMES[c] for c in COMPONENTS if c in self.components)

    def __str__(self) -> str:
        return self.name


ALL_SETTINGS = tuple(WeatherSetting(frozenset(n.split("+"))) for n in ALL_SETTING_NAMES)


def _valid_tokens_message() -> str:
    return ("valid tokens: H|haze|fog, R|rain, S|snow, joined with '+' (e.g. H+R or haze+rain), "
            "settings separated by ',', or 'all' for " + ",".join(ALL_SETTING_NAMES))


def parse_setting(text: str) -> WeatherSetting:
    """Parse one setting such as ``"H+R"``, ``"haze+snow"`` or ``"s"``."""
    parts = [p.strip().lower() for p in text.split("+")]
    if not text.strip() or any(not p for p in parts):
        raise NimbusError(f"empty weather component in {text!r}; {_valid_tokens_message()}")
    comps = []
    for p in parts:
        if p not in _ALIASES:
            raise NimbusError(f"unknown weather token {p!r} in {text!r}; {_valid_tokens_message()}")
        comps.append(_ALIASES[p])
    if len(set(comps)) != len(comps):
        raise NimbusError(f"weather setting {text!r} repeats a component; {_valid_tokens_message()}")
    return WeatherSetting(frozenset(comps))


def parse_weather(spec: str) -> tuple[WeatherSetting, ...]:
    """Parse a ``--weather`` value into settings (duplicates dropped, first order kept).

    Raises
    ------
    NimbusError
        On an unknown or empty token, listing the valid ones.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise NimbusError(f"no weather given; {_valid_tokens_message()}")
    out: list[WeatherSetting] = []
    for item in spec.split(","):
        item = item.strip()
        if item.lower() == "all":
            found = list(ALL_SETTINGS)
        else:
            found = [parse_setting(item)]
        out += [s for s in found if s not in out]
    return tuple(out)
