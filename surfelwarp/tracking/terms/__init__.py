"""The energy terms of the non-rigid solve, one file each, behind one small interface.

A term is built once per solve from the solve's inputs (`Problem`) by the factory registered
under its name, and then, at every Gauss-Newton iteration, adds its J^T W J blocks and J^T W r to
the iteration's normal equations (`linearize`) and gives its energy at candidate fields
(`energy`). The solve sums the terms named in `NonRigidParams.terms`, in that order. A new term
is one more file in this folder that registers a factory:

    @register("point_prior")
    def build(problem: Problem) -> Term | None:   # None: the term is off for this solve
        return PointPrior(...)

and its name in the config (`[tracking.nonrigid] terms = [..., "point_prior"]`).
"""
from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from surfelwarp.deform.warp_field import WarpField
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.tracking.assembly import NormalEquations
from surfelwarp.tracking.association import DepthPairs
from surfelwarp.tracking.free_space import FreeSpace

if TYPE_CHECKING:     # the solve that builds the terms imports this module
    from surfelwarp.tracking.anchors import AnchorTerm
    from surfelwarp.tracking.features import AnchoredMatches
    from surfelwarp.tracking.gauss_newton import NonRigidParams

ROBUST = ("none", "huber", "tukey")


@dataclass(frozen=True, eq=False)
class Problem:
    """What one solve is given: the start field, the solved surfels (reference positions and
    normals as components (3, N), their skinning), the depth observation and the parameters."""
    field: WarpField
    ref_points: np.ndarray
    ref_normals: np.ndarray
    knn: np.ndarray
    weights: np.ndarray
    depth_vertex_map: np.ndarray      # (H, W, 3) camera frame
    depth_normal_map: np.ndarray
    depth_valid: np.ndarray
    intrinsics: Intrinsics
    T_camera_to_world: np.ndarray
    params: NonRigidParams
    anchor: AnchorTerm | None = None
    depth_beyond: np.ndarray | None = None
    free_space: FreeSpace | None = None   # the observation's, at any pose (built if None)
    matches: AnchoredMatches | None = None   # colour features on the solved surfels


@dataclass(frozen=True, eq=False)
class Iterate:
    """One field the solve visits and what its warp gives the solved surfels: node dual
    quaternions, blends (N, 8), signed skinning weights (N, k), live points and normals (3, N);
    the depth pairs of the iteration (associated at its linearisation point) and, for a
    candidate, the step of the border unknown that goes with it (None: none taken)."""
    field: WarpField
    dq: np.ndarray
    blends: np.ndarray
    signed: np.ndarray
    live: np.ndarray
    live_normals: np.ndarray
    pairs: DepthPairs
    border_step: np.ndarray | None = None


class Term(Protocol):
    name: str

    def linearize(self, at: Iterate, system: NormalEquations) -> float:
        """Add the term's blocks and gradient at `at` to `system`; its energy there."""

    def energy(self, at: Iterate) -> float:
        """The term's energy at a candidate (over the iteration's pairs)."""


class BaseTerm:
    """Defaults of the optional hooks: a term with no state of its own across iterations."""
    name = "term"

    def accept(self, at: Iterate) -> None:
        """`at` became the solve's current field."""

    def finish(self, field: WarpField, free: np.ndarray) -> WarpField:
        """The field the solve returns; `free` the nodes it solved."""
        return field


_FACTORIES: dict[str, Callable[[Problem], Term | None]] = {}


def register(name: str):
    """Decorator: the factory of the term called `name` in NonRigidParams.terms."""
    def add(factory):
        _FACTORIES[name] = factory
        return factory
    return add


def known_terms() -> tuple[str, ...]:
    _load_all()
    return tuple(sorted(_FACTORIES))


def build_terms(names, problem: Problem) -> list[Term]:
    """The terms named, in order, each built for this solve (those that are off left out)."""
    _load_all()
    unknown = [n for n in names if n not in _FACTORIES]
    if unknown:
        raise ValueError(f"unknown term(s) {unknown}; known: {', '.join(sorted(_FACTORIES))}")
    terms = []
    for name in names:
        term = _FACTORIES[name](problem)
        if term is not None:
            term.name = name
            terms.append(term)
    return terms


_LOADED: list[bool] = []


def _load_all() -> None:
    """Import every module of this folder once: their factories register themselves."""
    if not _LOADED:
        for info in pkgutil.iter_modules(__path__):
            importlib.import_module(f"{__name__}.{info.name}")
        _LOADED.append(True)


def robust(r: np.ndarray, kind: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-residual cost rho(r) (~ r^2 near 0) and IRLS weight rho'(r) / (2 r)."""
    a = np.abs(r)
    if kind == "none":
        return r * r, np.ones_like(r)
    if kind == "huber":
        inside = a <= scale
        return np.where(inside, r * r, 2 * scale * a - scale * scale), np.where(inside, 1.0, scale / np.maximum(a, 1e-300))
    if kind == "tukey":
        s = np.clip(1 - (r / scale) ** 2, 0.0, None)
        return scale * scale / 3 * (1 - s ** 3), s * s
    raise ValueError(f"robust must be one of {ROBUST}, got {kind!r}")
