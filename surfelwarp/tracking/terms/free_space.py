"""The free-space term (free_space.py): model points where the camera saw through them are pulled
back towards the nearest pixel where it saw something, under Huber's penalty.

Its Jacobian is the data term's with the residual's gradient for a normal. It comes after the
rest anchors in the term list: its pull at an edge is not a node's own motion, so it takes no
part in the anchors' release test.
"""
from __future__ import annotations

import numpy as np

from surfelwarp.tracking.assembly import NormalEquations, sparse_point_blocks
from surfelwarp.tracking.free_space import FreeSpace, SilhouetteParams
from surfelwarp.tracking.terms import BaseTerm, Iterate, Problem, register, robust


class FreeSpaceTerm(BaseTerm):
    def __init__(self, free_space: FreeSpace, params: SilhouetteParams, ref_points: np.ndarray):
        self.free_space, self.params, self.ref_points = free_space, params, ref_points
        self._last = None       # (live points, live normals, what seen_through gave there)

    def seen_through(self, at: Iterate):
        """(energy, points, residuals, gradients (3, S), IRLS weights) at the live points: the
        points the camera saw through (and facing it) and theirs. An accepted candidate is the
        next linearisation point with the same live arrays (re-associated, not warped again), so
        the last answer is kept for them: 5.5 -> 3.3 evaluations a sheet frame."""
        if self._last is not None and self._last[0] is at.live and self._last[1] is at.live_normals:
            return self._last[2]
        r, grad = self.free_space.residuals(at.live)
        sel = np.flatnonzero(r > 0)
        sel = sel[self.free_space.facing(at.live[:, sel], at.live_normals[:, sel])]
        cost, w = robust(r[sel], "huber", self.params.huber_m)
        weight = self.params.weight
        out = weight * float(np.sum(cost)), sel, r[sel], grad[:, sel], weight * w
        self._last = (at.live, at.live_normals, out)
        return out

    def energy(self, at: Iterate) -> float:
        return self.seen_through(at)[0]

    def linearize(self, at: Iterate, system: NormalEquations) -> float:
        e, sel, r, grad, w = self.seen_through(at)
        if len(sel):
            slots, blocks, g = sparse_point_blocks(system.pattern, sel, at.blends, at.signed, self.ref_points, grad.T,
                                                   system.D, r, w)
            system.add(g, upper=blocks, slots=slots)
        return e


@register("free_space")
def build(problem: Problem) -> FreeSpaceTerm | None:
    params = problem.params.silhouette
    if params.weight <= 0:
        return None
    if problem.free_space is not None and problem.free_space.params == params:
        free_space = problem.free_space.moved_to(problem.T_camera_to_world)
    else:
        free_space = FreeSpace(np.asarray(problem.depth_vertex_map)[..., 2], problem.intrinsics,
                               problem.T_camera_to_world, params, problem.depth_beyond)
    return FreeSpaceTerm(free_space, params, problem.ref_points)
