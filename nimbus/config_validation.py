"""Validation of config dataclasses against a declarative table of accepted values.

Each config class keeps its table ``{field name: Limit}`` in its ``LIMITS`` class attribute
(:func:`limits_of`).  The Python type a field takes is read from its annotation (``int``,
``float``, ``bool``, ``str``, ``tuple[float, float]``, ``tuple[float, float, float] | None``,
...); the table adds the range.  One checker, :func:`field_problem`, serves both the
dataclasses' ``__post_init__`` (:func:`validate`) and the ``--set key=value`` engine
(:mod:`nimbus.config_set`, through :func:`check_field`, which names the value as typed), so a
bad value is refused at the boundary with a message that names the key, the value and what
is accepted, e.g. ``--set checkpoint_interval=0: must be an integer >= 1``.

Rules that hold for every field, whatever its table entry says:

* a number is never NaN, and is finite unless its limit says ``finite=False``;
* an ``int`` field takes an integer (not a bool, not 2.5) of at most :data:`INT_MAX`
  unless its limit sets ``hi`` (integers reach C++ kernels and tensor sizes as 32-bit ints);
* a fixed-length tuple field takes exactly that many items, each checked against the limit;
* a numeric field with no table entry is a programming error (``TypeError``), so a new
  field cannot slip in unvalidated.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import types
import typing
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from nimbus.errors import NimbusError

#: Largest integer an ``int`` field takes unless its limit sets ``hi``.
INT_MAX = 2**31 - 1


@dataclass(frozen=True)
class Limit:
    """The values one config field accepts (its type comes from the field's annotation).

    Attributes
    ----------
    lo, hi : float or None
        Bounds of a number, or of every item of a tuple; None: unbounded (``int`` fields:
        ``hi`` defaults to :data:`INT_MAX`; ``math.inf`` lifts that cap).
    lo_open, hi_open : bool
        Exclude the bound itself (``lo=0, lo_open=True``: ``> 0``).
    finite : bool
        Refuse +-inf (NaN is always refused).  False where inf means something (an opaque medium).
    also : tuple
        Values accepted outside ``[lo, hi]``, e.g. 0 meaning "off".
    ordered : bool
        A ``(lo, hi)`` pair: the first item may not exceed the second.
    choices : tuple of str
        The accepted values of a ``str`` field (empty: any string).
    scalar : bool
        A fixed-length tuple field also takes one number (its consumer broadcasts it).
    note : str
        What a special value means, shown in the message in parentheses.
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    finite: bool = True
    also: tuple = ()
    ordered: bool = False
    choices: tuple[str, ...] = ()
    scalar: bool = False
    note: str = ""


def at_least(lo: float, **kw) -> Limit:
    """``>= lo``."""
    return Limit(lo=lo, **kw)


def positive(**kw) -> Limit:
    """``> 0``."""
    return Limit(lo=0, lo_open=True, **kw)


def between(lo: float, hi: float, **kw) -> Limit:
    """In ``[lo, hi]`` (``lo_open`` / ``hi_open`` exclude an end)."""
    return Limit(lo=lo, hi=hi, **kw)


def fraction(**kw) -> Limit:
    """In ``[0, 1]``: a probability, an opacity, a colour value."""
    return Limit(lo=0, hi=1, **kw)


def one_of(*choices: str) -> Limit:
    """A ``str`` field taking one of ``choices``."""
    return Limit(choices=tuple(choices))


@dataclass(frozen=True)
class _Shape:
    """What a field's annotation says about its values."""

    base: type          # int, float, bool, str, or another type (a dataclass: not checked here)
    length: int | None  # 0: a scalar; n: a tuple of exactly n; None: a tuple of any length
    optional: bool      # None accepted


@functools.lru_cache(maxsize=None)
def field_shapes(cls: type) -> dict[str, _Shape]:
    """Each field of the dataclass ``cls``: its base type, tuple length and whether None is allowed."""
    hints = typing.get_type_hints(cls)
    return {f.name: _shape(hints[f.name]) for f in dataclasses.fields(cls)}


def _shape(tp: Any) -> _Shape:
    optional = False
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        optional = len(args) < len(typing.get_args(tp))
        tp = args[0] if len(args) == 1 else object
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return _Shape(args[0], None, optional)
        return _Shape(args[0] if len(set(args)) == 1 else object, len(args), optional)
    return _Shape(tp, 0, optional)


def _numeric(shape: _Shape) -> bool:
    return shape.base in (int, float)


def _fmt(x: float) -> str:
    return "inf" if x == math.inf else str(x) if isinstance(x, numbers.Integral) else f"{x:g}"


def describe(shape: _Shape, limit: Limit) -> str:
    """What a field accepts, in words: ``an integer >= 1``, ``(lo, hi), 2 numbers in [0, 1] with lo <= hi``."""
    notes = [limit.note] if limit.note else []
    if shape.base is bool:
        text = "true or false"
    elif shape.base is str:
        text = f"one of {', '.join(limit.choices)}" if limit.choices else "a string"
    else:
        integer = shape.base is int
        lo = limit.lo
        hi = None if limit.hi == math.inf else limit.hi  # an int field's default cap is told only when hit
        both = lo is not None and hi is not None
        noun = "an integer" if integer else "a finite number" if limit.finite and not both else "a number"
        if integer and both:
            text = f"{noun} in {_fmt(lo)}..{_fmt(hi)}"
        elif both:
            text = f"{noun} in {'(' if limit.lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if limit.hi_open else ']'}"
        elif lo is not None:
            text = f"{noun} {'>' if limit.lo_open else '>='} {_fmt(lo)}"
        elif hi is not None:
            text = f"{noun} {'<' if limit.hi_open else '<='} {_fmt(hi)}"
        else:
            text = noun
        if limit.also:
            text = f"{' or '.join(_fmt(a) for a in limit.also)} or {text}"
        if not limit.finite and "inf" not in limit.note:
            notes.insert(0, "inf allowed")
        if shape.length == 2 and limit.ordered:
            text = f"(lo, hi), 2 items each {text}, with lo <= hi"
        elif shape.length:
            text = f"{shape.length} items each {text}"
            if limit.scalar:
                notes.insert(0, "or one, used for all")
        elif shape.length is None:
            text = f"a list, each item {text}"
    if notes:
        text += f" ({'; '.join(notes)})"
    return text + (", or null" if shape.optional else "")


def _item_ok(shape: _Shape, limit: Limit, v: Any) -> bool:
    if shape.base is int:
        if not isinstance(v, numbers.Integral) or isinstance(v, (bool, np.bool_)):
            return False
    elif not isinstance(v, numbers.Real) or isinstance(v, (bool, np.bool_)) or math.isnan(v):
        return False
    if v in limit.also:
        return True
    if limit.finite and math.isinf(v):
        return False
    hi = limit.hi if limit.hi is not None else (INT_MAX if shape.base is int else None)
    if limit.lo is not None and not (v > limit.lo if limit.lo_open else v >= limit.lo):
        return False
    return hi is None or (v < hi if limit.hi_open else v <= hi)


def _ok(shape: _Shape, limit: Limit, value: Any) -> bool:
    if value is None:
        return shape.optional
    if shape.base is bool:
        return isinstance(value, (bool, np.bool_))
    if shape.base is str:
        return isinstance(value, str) and (not limit.choices or value in limit.choices)
    if shape.length == 0 or (limit.scalar and isinstance(value, numbers.Real)):
        return _item_ok(shape, limit, value)
    if not isinstance(value, (tuple, list)) or shape.length not in (None, len(value)):
        return False
    if not all(_item_ok(shape, limit, v) for v in value):
        return False
    return not limit.ordered or value[0] <= value[1]


def field_problem(cls: type, name: str, value: Any, limits: Mapping[str, Limit]) -> str | None:
    """None if ``value`` is acceptable for field ``name`` of config class ``cls``, else ``"must be ..."``.

    Fields of another type (nested dataclasses, tuples of layer specs) are left to their own class.
    """
    shape = field_shapes(cls)[name]
    limit = limits.get(name)
    if limit is None:
        if _numeric(shape):
            raise TypeError(f"{cls.__name__}.{name} is numeric but has no entry in its limits table")
        limit = Limit()
    if shape.base not in (int, float, bool, str) or _ok(shape, limit, value):
        return None
    items = value if isinstance(value, (tuple, list)) else (value,)
    over = shape.base is int and limit.hi is None and any(
        isinstance(v, numbers.Integral) and v > INT_MAX for v in items)
    return f"must be {describe(shape, limit)}" + (f" and at most {INT_MAX}" if over else "")


def check_field(cls: type, name: str, value: Any, limits: Mapping[str, Limit], given: str | None = None,
                example: str | None = None) -> None:
    """Raise :class:`NimbusError` ``"<given>: must be ..."`` if ``value`` does not fit field ``name``.

    ``given`` is how the user wrote it (``"--set near_plane=nan"``; default ``name=value``);
    ``example`` a well-formed value in the same syntax, added to the message.
    """
    problem = field_problem(cls, name, value, limits)
    if problem:
        raise NimbusError(f"{given or f'{name}={value!r}'}: {problem}" + (f", e.g. {example}" if example else ""))


def limits_of(cls: type) -> Mapping[str, Limit]:
    """The table of accepted values of config class ``cls`` (its ``LIMITS``; empty if it has none)."""
    return getattr(cls, "LIMITS", {})


def validate(config: Any, limits: Mapping[str, Limit] | None = None) -> None:
    """Check every field of the dataclass instance ``config`` (first failure raises :class:`NimbusError`).

    ``limits`` defaults to the class's own table (:func:`limits_of`).  Fields holding another
    config dataclass (``SynthConfig.haze``) are checked the same way against their class's table.
    """
    cls = type(config)
    limits = limits_of(cls) if limits is None else limits
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            validate(value)
        else:
            check_field(cls, f.name, value, limits)
