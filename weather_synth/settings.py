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

Protocol families (:func:`parse_family_weather`, the benchmark's ``--weathers``)
------------------------------------------------------------------------------
The same setting synthesised under another protocol (:mod:`weather_synth.config`) is
another benchmark setting: ``SETTING@PROTOCOL`` names it (``H@physical``,
``all@physical`` for the seven).  A setting without ``@`` is in the default family
(``onerestore``, the paper's data) and keeps its plain name, so ``H`` and
``H@onerestore`` are one setting, named ``H``.
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


#: Joins a setting to its protocol family in a benchmark token (``H+R@physical``).
FAMILY_SEPARATOR = "@"
#: The protocol of a setting named without ``@`` (the paper's data).
DEFAULT_PROTOCOL = "onerestore"


@dataclass(frozen=True)
class FamilySetting:
    """A weather setting in a synthesis-protocol family (module docstring).

    Attributes
    ----------
    setting : WeatherSetting
    protocol : str
        :data:`weather_synth.config.PROTOCOLS` name.
    """

    setting: WeatherSetting
    protocol: str = DEFAULT_PROTOCOL

    @property
    def name(self) -> str:
        """``H+R`` in the default family, ``H+R@physical`` in another."""
        if self.protocol == DEFAULT_PROTOCOL:
            return self.setting.name
        return f"{self.setting.name}{FAMILY_SEPARATOR}{self.protocol}"

    @property
    def description(self) -> str:
        """``haze + rain`` in the default family, ``haze + rain, physical protocol`` in another."""
        if self.protocol == DEFAULT_PROTOCOL:
            return self.setting.description
        return f"{self.setting.description}, {self.protocol} protocol"

    def __str__(self) -> str:
        return self.name


def _protocol(text: str, token: str) -> str:
    from weather_synth.config import PROTOCOLS  # the synthesizer's config: loaded only for a family token

    protocol = text.strip().lower()
    if protocol not in PROTOCOLS:
        raise NimbusError(f"unknown protocol {text!r} in {token!r}; write SETTING@PROTOCOL with a protocol among "
                          f"{', '.join(PROTOCOLS)} (e.g. H+R@physical, all@physical)")
    return protocol


def parse_family_setting(text: str) -> FamilySetting:
    """Parse one ``SETTING[@PROTOCOL]`` such as ``"H+R"`` or ``"haze@physical"``."""
    setting, sep, protocol = text.partition(FAMILY_SEPARATOR)
    return FamilySetting(parse_setting(setting), _protocol(protocol, text) if sep else DEFAULT_PROTOCOL)


def parse_family_weather(spec: str) -> tuple[FamilySetting, ...]:
    """Parse a benchmark ``--weathers`` value: :func:`parse_weather`'s grammar, each item optionally ``@PROTOCOL``.

    ``all@physical`` is the seven settings in the physical family.  Duplicates are dropped,
    first order kept.

    Raises
    ------
    NimbusError
        On an unknown or empty token or protocol.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise NimbusError(f"no weather given; {_valid_tokens_message()}")
    out: list[FamilySetting] = []
    for item in spec.split(","):
        setting, sep, protocol = item.strip().partition(FAMILY_SEPARATOR)
        family = _protocol(protocol, item.strip()) if sep else DEFAULT_PROTOCOL
        found = [FamilySetting(s, family) for s in parse_weather(setting)] if setting.strip() else []
        if not found:
            raise NimbusError(f"empty weather setting in {item.strip()!r}; {_valid_tokens_message()}")
        out += [s for s in found if s not in out]
    return tuple(out)


def family_order() -> tuple[str, ...]:
    """Every setting name of every family, in table order: the default family's seven, then each other's."""
    from weather_synth.config import PROTOCOLS

    others = [p for p in PROTOCOLS if p != DEFAULT_PROTOCOL]
    return ALL_SETTING_NAMES + tuple(FamilySetting(s, p).name for p in others for s in ALL_SETTINGS)
