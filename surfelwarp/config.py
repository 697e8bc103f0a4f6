"""Overriding any method's parameter tree (frozen dataclasses) from a TOML or JSON file.

A config file nests tables like the tree (`surfelwarp run ... --config FILE`, for either method):

    [fusion]
    distance_threshold_m = 0.008
    [tracking.nonrigid]
    lambda_reg = 8.0
    [reinit]
    every_frames = 50

Keys not given keep their defaults. An unknown key or a value of the wrong type is an
InputError naming the file and the key. Every number (and every entry of a list of numbers)
must be finite and positive; a params class names in class attributes the exceptions and
bounds: `ZERO_OK` (0 is meaningful: a weight that turns a term off, a tolerance), `UNIT` (at
most 1: cosines, shares, fractions), `AT_MOST` (name -> largest sensible value: pixel windows,
counts that size an allocation, None: no bound; a length, a name ending in `_m`, is at most
LENGTH_AT_MOST_M unless named there), and `CHOICES` (the values a string field may take); a
`problems()` method adds constraints between values (key -> whether it is out of range, or
what is wrong with it).
"""
from __future__ import annotations

import json
import math
import types
import typing
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

from surfelwarp.errors import InputError


# Metres beyond what a depth camera sees: no node radius or gate is longer. Without a bound a
# node radius of 1e300 ran to the end and wrote NaN positions.
LENGTH_AT_MOST_M = 10.0


def _bad(path, key: str, problem: str) -> InputError:
    return InputError(path, f"config key '{key}': {problem}")


def _value(value, hint, path, key: str, choices: dict = {}):
    """`value` checked against the type hint `hint` (float, int, bool, str, X | None, tuple[X, ...])."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return None if value is None and len(args) < len(typing.get_args(hint)) else _value(value, args[0], path, key,
                                                                                              choices)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _bad(path, key, f"expected a list, got {value!r}")
        return tuple(_value(v, typing.get_args(hint)[0], path, key, choices) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise _bad(path, key, f"expected true or false, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise _bad(path, key, f"expected a string, got {value!r}")
        name = key.rsplit(".", 1)[-1]
        if name in choices and value not in choices[name]:
            raise _bad(path, key, f"expected one of {', '.join(choices[name])}, got {value!r}")
        return value
    if hint in (int, float):
        ok = isinstance(value, int) if hint is int else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok:
            raise _bad(path, key, f"expected {'an integer' if hint is int else 'a number'}, got {value!r}")
        try:
            return hint(value)          # its range: check() (range_problem)
        except OverflowError:
            raise _bad(path, key, f"out of range, got {value!r}") from None
    raise _bad(path, key, f"cannot be set from a config file ({hint})")


def override(params, table: dict, path=None, prefix: str = ""):
    """A copy of the dataclass `params` with the values of the (nested) dict `table`."""
    hints = typing.get_type_hints(type(params))
    names = {f.name for f in fields(params)}
    changes = {}
    for name, value in table.items():
        key = prefix + name
        if name not in names:
            raise _bad(path, key, f"unknown key (known here: {', '.join(sorted(names))})")
        current = getattr(params, name)
        if is_dataclass(current):
            if not isinstance(value, dict):
                raise _bad(path, key, "expected a table of parameters")
            changes[name] = override(current, value, path, key + ".")
        else:
            changes[name] = _value(value, hints[name], path, key, getattr(type(params), "CHOICES", {}))
    try:
        return replace(params, **changes)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"config table '{prefix.rstrip('.') or '(top)'}': {exc}") from None


def read_table(path: Path) -> dict:
    """The file's contents as a dict: TOML (.toml) or JSON (anything else)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the config file ({exc.__class__.__name__})") from None
    try:
        if path.suffix.lower() == ".toml":
            try:
                import tomllib
            except ImportError:
                raise InputError(path, "TOML config files need Python 3.11+; use JSON") from None
            table = tomllib.loads(text)
        else:
            table = json.loads(text)
    except (ValueError, TypeError) as exc:   # tomllib.TOMLDecodeError and JSONDecodeError are ValueErrors
        raise InputError(path, f"config file does not parse ({exc})") from None
    if not isinstance(table, dict):
        raise InputError(path, "config file must hold a table of parameters")
    return table


def range_problem(params, name: str) -> str | None:
    """What is wrong with the number(s) in field `name` of `params` by its class's ZERO_OK, UNIT
    and AT_MOST (None: nothing)."""
    cls, value = type(params), getattr(params, name)
    values = value if isinstance(value, tuple) else (value,)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return None
    low_ok = name in getattr(cls, "ZERO_OK", ())
    length = LENGTH_AT_MOST_M if name.endswith("_m") else None
    high = 1 if name in getattr(cls, "UNIT", ()) else getattr(cls, "AT_MOST", {}).get(name, length)
    for v in values:
        if not math.isfinite(v) or v < 0 or (v == 0 and not low_ok) or (high is not None and v > high):
            span = f"{'[0' if low_ok else '(0'}, {'inf)' if high is None else f'{high}]'}"
            return f"must be in {span}, got {v!r}"
    return None


def check(params, path=None, prefix: str = ""):
    """`params` if every number in its tree is in range (range_problem) and no class reports a
    problem (params.problems()), else InputError."""
    for f in fields(params):
        problem = range_problem(params, f.name)
        if problem:
            raise _bad(path, prefix + f.name, problem)
    problems = params.problems() if hasattr(params, "problems") else {}
    for key, bad in problems.items():
        if bad:
            raise _bad(path, prefix + key, bad if isinstance(bad, str) else
                       "out of range (rigid lists need one entry per pyramid level; sizes and counts must be positive)")
    for f in fields(params):
        value = getattr(params, f.name)
        if is_dataclass(value):
            check(value, path, prefix + f.name + ".")
    return params


def load_params(path: Path, base):
    """`base` (any method's parameter tree) with the file's values."""
    return check(override(base, read_table(path), path), path)
