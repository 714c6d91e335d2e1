"""Checks shared by the configuration dataclasses: every failure names the field, the value and
what is expected.

Rules of the checkers below:

* numbers: Python and numpy integers and floats are accepted and normalised to a plain ``int``
  or ``float``; ``bool`` (and ``numpy.bool_``), ``str``, ``None`` and containers are not numbers
  (TypeError). NaN is always rejected and +-inf unless the field allows it (ValueError).
* integer fields accept any integral type (``numpy.int64(3)`` becomes ``3``) and reject floats,
  even integral ones such as ``3.0`` (ValueError: the type is numeric but the value is not an
  integer).
* tuples: any sequence (tuple, list, 1-D array) of the right length, normalised to a tuple, so
  the frozen dataclasses stay hashable; each entry is checked like a number, its index named.
* choices: the message lists the valid values.

A wrong kind of value (a string for a number) raises TypeError, a value of the right kind that
is out of range ValueError. Messages read like
``EnvConfig.n_uavs must be an integer >= 1, got '3' (str)``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np


def require(ok: bool, message: str) -> None:
    """Raise ValueError(message) unless ``ok``."""
    if not ok:
        raise ValueError(message)


def describe(value: Any) -> str:
    """``value`` as it appears in an error message: its repr and its type."""
    text = repr(value)
    if len(text) > 80:
        text = text[:77] + "..."
    return f"{text} ({type(value).__name__})"


def _fmt(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def number_expectation(
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    integer: bool = False,
    allow_inf: bool = False,
) -> str:
    """The text after "must be" for a number with these bounds, e.g. 'a finite number > 0'."""
    kind = "an integer" if integer else ("a number" if allow_inf else "a finite number")
    if lo is not None and hi is not None:
        left, right = "(" if lo_open else "[", ")" if hi_open else "]"
        return f"{kind} in {left}{_fmt(lo)}, {_fmt(hi)}{right}"
    if lo is not None:
        return f"{kind} {'>' if lo_open else '>='} {_fmt(lo)}"
    if hi is not None:
        return f"{kind} {'<' if hi_open else '<='} {_fmt(hi)}"
    return kind


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)


def check_number(
    owner: str,
    name: str,
    value: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    integer: bool = False,
    allow_inf: bool = False,
    none_means: str | None = None,
) -> Any:
    """``value`` as a plain int/float if it is a number within the bounds, else raise.

    ``none_means``: None is allowed and means this (e.g. "the world's"); it is returned as is.
    """
    if value is None and none_means is not None:
        return None
    expected = number_expectation(
        lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, integer=integer, allow_inf=allow_inf
    )
    if none_means is not None:
        expected = f"None ({none_means}) or {expected}"
    message = f"{owner}.{name} must be {expected}, got {describe(value)}"
    if not _is_number(value):
        raise TypeError(message)
    if integer:
        if not isinstance(value, numbers.Integral):
            raise ValueError(message)
        out: Any = int(value)
    else:
        out = float(value)
        if math.isnan(out) or (math.isinf(out) and not allow_inf):
            raise ValueError(message)
    if lo is not None and (out < lo or (lo_open and out == lo)):
        raise ValueError(message)
    if hi is not None and (out > hi or (hi_open and out == hi)):
        raise ValueError(message)
    return out


def choices_text(choices: Iterable[Any]) -> str:
    """``'a', 'b' or 'c'``."""
    items = [repr(c) for c in choices]
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} or {items[-1]}"


def check_choice(owner: str, name: str, value: Any, choices: Sequence[Any]) -> Any:
    """``value`` if it is one of ``choices`` (compared by type and value), else ValueError
    listing them."""
    for c in choices:
        if (c is None and value is None) or (
            c is not None and isinstance(value, type(c)) and value == c
        ):
            return c
    raise ValueError(f"{owner}.{name} must be {choices_text(choices)}, got {describe(value)}")


def check_flag(owner: str, name: str, value: Any) -> bool:
    """``value`` as a bool if it is ``True``/``False`` (or a numpy bool), else TypeError."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    raise TypeError(f"{owner}.{name} must be True or False, got {describe(value)}")


def check_text(owner: str, name: str, value: Any) -> str:
    """``value`` if it is a non-empty string."""
    if not isinstance(value, str):
        raise TypeError(f"{owner}.{name} must be a non-empty string, got {describe(value)}")
    require(value != "", f"{owner}.{name} must be a non-empty string, got {describe(value)}")
    return value


def check_tuple(
    owner: str, name: str, value: Any, length: int | None = None, **bounds: Any
) -> tuple:
    """``value`` as a tuple of ``length`` numbers (any length >= 1 if None), each checked by
    `check_number` with ``bounds`` and named ``name[i]``."""
    size = "" if length is None else f"{length} "
    vector = isinstance(value, np.ndarray) and value.ndim == 1
    if not (vector or (isinstance(value, Sequence) and not isinstance(value, str | bytes))):
        raise TypeError(f"{owner}.{name} must be a tuple of {size}numbers, got {describe(value)}")
    items = list(value)
    if (length is not None and len(items) != length) or not items:
        raise ValueError(
            f"{owner}.{name} must be a tuple of {size or 'one or more '}numbers, "
            f"got {describe(value)} with {len(items)} entries"
        )
    return tuple(check_number(owner, f"{name}[{i}]", v, **bounds) for i, v in enumerate(items))


def check_range_pair(
    owner: str,
    name: str,
    value: Any,
    *,
    lo: float | None = None,
    lo_open: bool = False,
    hi: float | None = None,
    strict: bool = False,
    integer: bool = False,
) -> tuple:
    """``value`` as an ordered pair ``(a, b)``: a <= b (a < b if ``strict``), both numbers
    within ``lo``/``hi`` (bounds as in `check_number`)."""
    a, b = check_tuple(owner, name, value, 2, lo=lo, lo_open=lo_open, hi=hi, integer=integer)
    order = "<" if strict else "<="
    require(
        a < b if strict else a <= b,
        f"{owner}.{name} must be an ordered range (lo, hi) with lo {order} hi, "
        f"got {describe(value)}",
    )
    return a, b


class Fields:
    """Checks the fields of one (frozen) dataclass instance and writes the normalised values
    back, so downstream code sees plain ints, floats, bools and tuples.

    >>> f = Fields(self)
    >>> f.number("fx", lo=0, lo_open=True)
    """

    def __init__(self, obj: Any) -> None:
        self.obj = obj
        self.owner = type(obj).__name__

    def _set(self, name: str, value: Any) -> Any:
        object.__setattr__(self.obj, name, value)
        return value

    def number(self, name: str, **bounds: Any) -> Any:
        return self._set(name, check_number(self.owner, name, getattr(self.obj, name), **bounds))

    def integer(self, name: str, **bounds: Any) -> int:
        return self.number(name, integer=True, **bounds)

    def choice(self, name: str, choices: Sequence[Any]) -> Any:
        return self._set(name, check_choice(self.owner, name, getattr(self.obj, name), choices))

    def flag(self, name: str) -> bool:
        return self._set(name, check_flag(self.owner, name, getattr(self.obj, name)))

    def text(self, name: str) -> str:
        return self._set(name, check_text(self.owner, name, getattr(self.obj, name)))

    def tuple(self, name: str, length: int | None = None, **bounds: Any) -> tuple:
        value = check_tuple(self.owner, name, getattr(self.obj, name), length, **bounds)
        return self._set(name, value)

    def range_pair(self, name: str, **bounds: Any) -> tuple:
        value = check_range_pair(self.owner, name, getattr(self.obj, name), **bounds)
        return self._set(name, value)

    def instance(self, name: str, kind: type) -> Any:
        value = getattr(self.obj, name)
        if not isinstance(value, kind):
            raise TypeError(f"{self.owner}.{name} must be a {kind.__name__}, got {describe(value)}")
        return value
