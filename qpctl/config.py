"""A scenario key is declared once: as a field of the dataclass that uses its value.

The TOML schema of a table (:data:`qpctl.scenario.SCHEMA`) is generated from the fields of the
dataclasses behind it (:func:`schema_of`): the field's name is the key, its default (or default
factory) is the key's default, and its type annotation picks the checker that turns the TOML value
into a Python one or rejects it (:data:`CHECKERS`). A field whose type alone does not say how to
read it names its checker in its metadata (:func:`setting`), which may also carry its unit and a rule on
its value (:func:`check_fields`, called from the dataclass's ``__post_init__``, raises
:class:`~qpctl.errors.ConfigError` naming the key at construction, as mink's ``InvalidGain``).

Adding a ``[controller]`` key is therefore one field (with its docstring line) in
:class:`~qpctl.law.LawGains`, :class:`~qpctl.controllers.qp.QPConfig` or
:class:`~qpctl.controllers.config.ControllerConfig`, plus its line in the README's scenario reference.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from qpctl.errors import ConfigError

REQUIRED: Any = object()  # a key without a default: the scenario must give it

Checker = Callable[[Any], Any]  # returns the value read, or raises TypeError("what it must be")


def number(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError("a number")
    return float(v)


def integer(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise TypeError("an integer")
    return v


def boolean(v: Any) -> bool:
    if not isinstance(v, bool):
        raise TypeError("true or false")
    return v


def string(v: Any) -> str:
    if not isinstance(v, str):
        raise TypeError("a string")
    return v


def numbers(v: Any) -> list[float]:
    if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise TypeError("a list of numbers")
    return [float(x) for x in v]


def number_or_list(v: Any) -> float | list[float]:
    try:
        return number(v)
    except TypeError:
        try:
            return numbers(v)
        except TypeError:
            raise TypeError("a number or a list of numbers") from None


def points(v: Any) -> list[list[float]]:
    if not isinstance(v, list) or not v:
        raise TypeError("a non-empty list of points ([[x, y], ...])")
    pts = [numbers(p) for p in v]
    if len({len(p) for p in pts}) != 1:
        raise TypeError("points of equal length")
    return pts


def strings(v: Any) -> list[str]:
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise TypeError("a list of strings")
    return v


def number_or_auto(v: Any) -> float | str:
    if v == "auto":
        return "auto"
    try:
        return number(v)
    except TypeError:
        raise TypeError('a number or "auto"') from None


def name_pairs(v: Any) -> list[list[str]]:
    if not isinstance(v, list) or not all(isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p)
                                          for p in v):
        raise TypeError('a list of pairs of link names ([["a", "b"], ...])')
    return v


def table(v: Any) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise TypeError("a table")
    return v


# A field's type annotation (as written, ``from __future__ import annotations``) → its checker.
# ``X | None`` reads as X: None is the default of an optional key, never a value a TOML file gives.
CHECKERS: dict[str, Checker] = {
    "float": number,
    "int": integer,
    "bool": boolean,
    "str": string,
    "list[float]": numbers,
    "list[str]": strings,
    "list[list[str]]": name_pairs,
    "list[list[float]]": points,
    "float | list[float]": number_or_list,
    "float | tuple[float, ...]": number_or_list,
    "float | str": number_or_auto,
    "dict[str, Any]": table,
    "np.ndarray": numbers,
}

# Rules on a value (metadata ``valid``): (predicate, what the value must be).
RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "positive": (lambda v: math.isfinite(v) and v > 0, "a positive number"),
    "nonnegative": (lambda v: math.isfinite(v) and v >= 0, "a number >= 0"),
    "seconds": (lambda v: math.isfinite(v) and v > 0, "a positive number of seconds"),
    "distance_or_inf": (lambda v: v >= 0, "a number >= 0 (inf: no limit)"),
    "count_or_inf": (lambda v: v == math.inf or (v >= 1 and float(v).is_integer()), "a whole number >= 1 (inf: no limit)"),
}


def setting(default: Any = REQUIRED, *, factory: Callable[[], Any] | None = None, check: Checker | None = None,
            valid: str | None = None, choices: tuple[str, ...] = (), unit: str = "") -> Any:
    """A dataclass field that is a scenario key: its default (or ``factory``), and optionally the
    checker that reads its TOML value (when its type annotation does not say), a rule on its value
    (a name in :data:`RULES`, or the ``choices`` of a string; enforced by :func:`check_fields`) and its
    unit (``"m"``, ``"1/s"``). (ruff's RUF009 accepts it on immutable types only: for a list-typed
    key with metadata, write ``dataclasses.field(default_factory=..., metadata=...)``.)"""
    meta = {"check": check, "valid": valid, "choices": choices, "unit": unit}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    if default is REQUIRED:
        return dataclasses.field(metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _checker(f: dataclasses.Field[Any], owner: type) -> Checker:
    given = f.metadata.get("check")
    if given is not None:
        return given  # type: ignore[no-any-return]
    text = str(f.type).replace("Optional[", "").removesuffix(" | None")
    if text not in CHECKERS:
        raise TypeError(f"{owner.__name__}.{f.name}: no checker for type {f.type!r}; give one with setting(check=...)")
    return CHECKERS[text]


def _default(f: dataclasses.Field[Any]) -> Any:
    """The field's default as TOML would give it (an array as a list)."""
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return REQUIRED
    return value.tolist() if isinstance(value, np.ndarray) else value


def schema_of(*classes: type, skip: Iterable[str] = ()) -> dict[str, tuple[Checker, Any]]:
    """The schema of a table: ``{key: (checker, default)}`` from the dataclasses' fields, in order (a
    key declared by two of them is an error: each key is declared once)."""
    skipped = set(skip)
    out: dict[str, tuple[Checker, Any]] = {}
    for cls in classes:
        for f in dataclasses.fields(cls):
            if f.name in skipped or not f.init:
                continue
            if f.name in out:
                raise TypeError(f"key {f.name!r} is declared twice ({cls.__name__} and an earlier class)")
            out[f.name] = (_checker(f, cls), _default(f))
    return out


def check_fields(obj: Any, section: str) -> None:
    """Apply each field's ``valid`` rule and ``choices``; :class:`ConfigError` naming ``section.key``
    for the first broken."""
    for f in dataclasses.fields(obj):
        choices = f.metadata.get("choices")
        if choices and getattr(obj, f.name) not in choices:
            names = f"{', '.join(choices[:-1])} or {choices[-1]}" if len(choices) > 1 else choices[0]
            raise ConfigError(f"must be {names}, got {getattr(obj, f.name)!r}", key=f"{section}.{f.name}")
        rule = f.metadata.get("valid")
        val = getattr(obj, f.name)
        if rule is None or val == "auto":  # a number-or-"auto" key: the rule is on the number
            continue
        ok, what = RULES[rule]
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not ok(val):
            raise ConfigError(f"must be {what}, got {val!r}", key=f"{section}.{f.name}")
