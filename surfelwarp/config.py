"""Every SurfelWarp parameter in one frozen tree, and overriding it from a TOML or JSON file.

A config file nests tables like the tree (`surfelwarp run ... --config FILE`):

    [fusion]
    distance_threshold_m = 0.008
    [tracking.nonrigid]
    lambda_reg = 8.0
    [reinit]
    every_frames = 50

Keys not given keep their defaults. An unknown key or a value of the wrong type is an
InputError naming the file and the key.
"""
from __future__ import annotations

import json
import math
import types
import typing
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from pathlib import Path

from .appending import AppendParams
from .errors import InputError
from .fusion import FusionParams
from .nonrigid import LINEAR_SOLVERS, ROBUST
from .reinit import ReinitParams
from .tracking import CAMERAS, TrackingParams
from .warp_field import WarpFieldParams


@dataclass(frozen=True)
class SurfelWarpParams:
    warp_field: WarpFieldParams = field(default_factory=WarpFieldParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)
    fusion: FusionParams = field(default_factory=FusionParams)     # Sec. VI-A, VI-D removal
    append: AppendParams = field(default_factory=AppendParams)     # Sec. VI-B..D appending
    reinit: ReinitParams = field(default_factory=ReinitParams)     # Sec. VI-F
    # Solver maps draw the stable surfels (fusion.stable_confidence = delta_stable) first.
    # recent_draw 'fill_all': every other surfel only on pixels no stable surfel covers, so
    # fresh surfels (carrying last frame's pose error) never occlude the stable model, while
    # newly seen surface and the not yet stable model are tracked (a young model is all
    # unstable: a free sheet's edges, never observed again once they overhang, left the solve
    # and the sheet slid, EPE 61 mm against 22 mm); 'fill': only those observed within the
    # last recent_frames frames (delta_recent, Table 1); 'with': stable and recent in one
    # depth test.
    recent_frames: int = 2
    recent_draw: str = "fill_all"
    index_map_supersample: int = 4   # Sec. VI-A: 4x4 super-sampled index map

    def to_dict(self) -> dict:
        return asdict(self)


# String parameters with a fixed set of values, by field name.
CHOICES = {"robust": ROBUST, "linear_solver": LINEAR_SOLVERS, "recent_draw": ("fill", "fill_all", "with"), "camera": CAMERAS}


def _bad(path, key: str, problem: str) -> InputError:
    return InputError(path, f"config key '{key}': {problem}")


def _value(value, hint, path, key: str):
    """`value` checked against the type hint `hint` (float, int, bool, str, X | None, tuple[X, ...])."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return None if value is None and len(args) < len(typing.get_args(hint)) else _value(value, args[0], path, key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _bad(path, key, f"expected a list, got {value!r}")
        return tuple(_value(v, typing.get_args(hint)[0], path, key) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise _bad(path, key, f"expected true or false, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise _bad(path, key, f"expected a string, got {value!r}")
        name = key.rsplit(".", 1)[-1]
        if name in CHOICES and value not in CHOICES[name]:
            raise _bad(path, key, f"expected one of {', '.join(CHOICES[name])}, got {value!r}")
        return value
    if hint in (int, float):
        ok = isinstance(value, int) if hint is int else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok:
            raise _bad(path, key, f"expected {'an integer' if hint is int else 'a number'}, got {value!r}")
        if not math.isfinite(value) or value < 0:
            raise _bad(path, key, f"expected a finite non-negative value, got {value!r}")
        return hint(value)
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
            changes[name] = _value(value, hints[name], path, key)
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


def check(params: SurfelWarpParams, path=None) -> SurfelWarpParams:
    """Constraints between or on values that the types do not express."""
    rigid = params.tracking.rigid
    problems = {
        "tracking.rigid.iterations": len(rigid.iterations) != rigid.pyramid_levels,
        "tracking.rigid.distance_gate_m": len(rigid.distance_gate_m) != rigid.pyramid_levels,
        "tracking.rigid.pyramid_levels": rigid.pyramid_levels < 1,
        "warp_field.node_radius_m": params.warp_field.node_radius_m <= 0,
        "warp_field.k_skin": params.warp_field.k_skin < 1,
        "warp_field.graph_k": params.warp_field.graph_k < 1,
        "tracking.hierarchy.levels": params.tracking.hierarchy.levels < 1,
        "tracking.hierarchy.k": params.tracking.hierarchy.k < 1,
        "fusion.window": params.fusion.window < 1,
        "index_map_supersample": params.index_map_supersample < 1,
    }
    for key, bad in problems.items():
        if bad:
            raise _bad(path, key, "out of range (rigid lists need one entry per pyramid level; "
                                  "sizes and counts must be positive)")
    return params


def load_params(path: Path, base: SurfelWarpParams = SurfelWarpParams()) -> SurfelWarpParams:
    return check(override(base, read_table(path), path), path)
