"""``--set key=value``: one grammar for every tool's config overrides (nimbus-train, nimbus-synth, nimbus-bench).

:func:`apply_overrides` takes a frozen dataclass config and ``{key: text}`` and returns the
config with each value parsed by its field's annotation and checked against the field's
limits (:mod:`nimbus.config_validation`) before anything is set.

Keys
----
A field name (``iterations``), or a dotted path into nested dataclass configs
(``haze.beta``, ``rain.slices``).  An unknown key is refused with the valid keys at that
level (and the closest ones first); a group (``haze``) or a tuple of layer specs cannot be
set as a whole.

Values (by the field's type)
----------------------------
``bool``
    ``true`` / ``false``, also ``yes`` / ``no``, ``on`` / ``off``, ``1`` / ``0`` (any case).
``int``
    an integer; a number with no fraction also counts (``1e3``, ``3.0``).
``float``
    anything Python's ``float`` reads: ``0.5``, ``1e-4``, ``inf`` / ``Infinity``, ``nan`` / ``NaN``
    (the limits then refuse NaN, and inf where the field is finite).
``str``
    the text as typed (JSON quotes, ``"fog"``, are removed).
tuples
    items separated by commas, optionally in brackets: ``0.5,0.5,0.5``, ``[0.5, 0.5, 0.5]``,
    ``(0, inf)``; a field that broadcasts one number (the limit's ``scalar``) also takes ``0.8``.
optional fields
    ``null`` (or ``none``) for None.

Text that does not parse is handed to the limit check as typed, so the message says what is
accepted: ``--set iterations=many: must be an integer >= 1``.

A config class may define ``with_changes(self, changes: dict) -> config`` to apply settings that
move together (:class:`nimbus.train.config.TrainConfig` stretches its schedule when only
``iterations`` changes); otherwise the parsed values are applied with :func:`dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
from typing import Any, Iterable, Mapping, TypeVar

from nimbus.config_validation import Limit, check_field, field_shapes, limits_of
from nimbus.errors import NimbusError

C = TypeVar("C")

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")
_NULL = ("null", "none")
# How many near matches an unknown key's message names first.
_NEAR = 5


def parse_set_args(items: Iterable[str] | None, flag: str = "--set") -> dict[str, str]:
    """``["key=value", ...]`` from repeated ``--set`` flags -> ``{key: value}`` (a later key wins); ``flag``
    names the option in the error message."""
    out: dict[str, str] = {}
    for item in items or []:
        if "=" not in item:
            raise NimbusError(f"{flag} expects key=value, got {item!r}")
        key, raw = item.split("=", 1)
        out[key.strip()] = raw.strip()
    return out


def apply_overrides(config: C, overrides: Mapping[str, str]) -> C:
    """``config`` (a frozen dataclass) with every ``{key: text}`` override parsed, checked and applied.

    Raises
    ------
    NimbusError
        An unknown key, a group key, or a value its field does not accept; the message
        names the override as typed (``--set haze.beta=-1: must be a number >= 0 ...``).
    """
    changes: dict[str, Any] = {}
    for key, raw in overrides.items():
        path = key.split(".")
        owner, level = config, changes
        for depth, name in enumerate(path):
            _check_key(owner, name, key, last=depth == len(path) - 1)
            if depth < len(path) - 1:
                owner, level = getattr(owner, name), level.setdefault(name, {})
        level[path[-1]] = _parse_field(owner, path[-1], key, raw)
    return _apply(config, changes)


def _apply(obj: C, changes: dict[str, Any]) -> C:
    """Nested ``changes`` applied bottom-up, each level through its class's ``with_changes`` if it has one."""
    flat = {k: _apply(getattr(obj, k), v) if isinstance(v, dict) else v for k, v in changes.items()}
    if not flat:
        return obj
    with_changes = getattr(obj, "with_changes", None)
    return with_changes(flat) if with_changes is not None else dataclasses.replace(obj, **flat)


def _check_key(obj: Any, name: str, key: str, last: bool) -> None:
    names = [f.name for f in dataclasses.fields(obj)]
    if name not in names:
        near = difflib.get_close_matches(name, names, n=_NEAR, cutoff=0.6)
        hint = f"did you mean {', '.join(near)}? " if near else ""
        raise NimbusError(f"unknown setting {key!r}; {hint}valid keys here: {', '.join(sorted(names))}")
    value = getattr(obj, name)
    if not last and not dataclasses.is_dataclass(value):
        raise NimbusError(f"{key!r}: {name} has no sub-settings")
    if last and dataclasses.is_dataclass(value):
        raise NimbusError(f"{key!r} is a group of settings; set one of its keys, e.g. {key}.<key>")
    if last and isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
        raise NimbusError(f"{key!r} is a list of layer specs; change it in Python (or use the scale settings)")


def _parse_field(obj: Any, name: str, key: str, raw: str) -> Any:
    """``raw`` parsed as field ``name`` of ``obj`` and checked against its limit."""
    cls = type(obj)
    shape, limits = field_shapes(cls)[name], limits_of(cls)
    limit = limits.get(name, Limit())
    if shape.base not in (bool, int, float, str):
        raise NimbusError(f"{key!r} cannot be set with --set; change it in Python")
    value = parse_text(raw, shape.base, shape.length, shape.optional, limit.scalar)
    current = getattr(obj, name)
    example = f"{key}={','.join(map(str, current))}" if isinstance(current, tuple) else None
    check_field(cls, name, value, limits, given_as(key, raw), example)
    return value


def parse_text(raw: str, base: type, length: int | None = 0, optional: bool = False, scalar: bool = False) -> Any:
    """``raw`` as a value of type ``base`` (``length`` 0: a scalar, n / None: a tuple); ``raw`` itself if it
    does not parse (the caller's check then refuses it with the accepted values)."""
    text = raw.strip()
    if optional and text.lower() in _NULL:
        return None
    if base is str:
        return _unquote(text)
    if length == 0:
        return _scalar(text, base, raw)
    inner = text.strip("[]()")
    if scalar and "," not in inner:
        single = _scalar(inner, base, raw)
        if single is not raw:
            return single
    items = [_scalar(p.strip(), base, raw) for p in inner.split(",") if p.strip()]
    return raw if any(v is raw for v in items) else tuple(items)


def _scalar(text: str, base: type, raw: str) -> Any:
    if base is bool:
        return True if text.lower() in _TRUE else False if text.lower() in _FALSE else raw
    try:
        number = float(text)
    except ValueError:
        return raw
    if base is float:
        return number
    if text.lstrip("+-").isdigit():
        try:
            return int(text)  # exact, beyond float precision
        except ValueError:  # more digits than Python converts
            return raw
    return int(number) if number.is_integer() else number  # 1e3 -> 1000; 2.5 and inf are refused by the check


def _unquote(text: str) -> str:
    if len(text) >= 2 and text[0] == text[-1] == '"':
        try:
            value = json.loads(text)
        except ValueError:
            return text
        return value if isinstance(value, str) else text
    return text


def given_as(key: str, raw: str) -> str:
    """How a ``--set`` item is quoted in messages (a huge value is shortened)."""
    return f"--set {key}={raw if len(raw) <= 60 else raw[:40] + f'... ({len(raw)} characters)'}"
