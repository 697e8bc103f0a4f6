"""The data term (SurfelWarp Eq. 9, DynamicFusion Eq. 7): sum_c rho(n_c . (W(v_c) v_c - d_c)).

The model surfels v_c are warped into the live (world) frame and paired with the depth pixel
they project to (association.py); d_c, n_c are that pixel's vertex and normal in world. The
Jacobian is the exact derivative of the dual quaternion blend (blend_jacobian.py), summed in
factored form (assembly.point_blocks). rho is NonRigidParams.robust.
"""
from __future__ import annotations

import numpy as np

from surfelwarp.tracking.assembly import NormalEquations, point_blocks
from surfelwarp.tracking.terms import BaseTerm, Iterate, Problem, register, robust


class DepthTerm(BaseTerm):
    def __init__(self, ref_points: np.ndarray, kind: str, scale_m: float):
        self.ref_points, self.kind, self.scale_m = ref_points, kind, scale_m

    def residuals(self, at: Iterate) -> np.ndarray:
        pairs = at.pairs
        return np.einsum("ci,ic->c", pairs.normals, at.live[:, pairs.index] - pairs.points.T)

    def energy(self, at: Iterate) -> float:
        return float(np.sum(robust(self.residuals(at), self.kind, self.scale_m)[0]))

    def linearize(self, at: Iterate, system: NormalEquations) -> float:
        cost, w = robust(r := self.residuals(at), self.kind, self.scale_m)
        blocks, g = point_blocks(system.pattern, at.pairs.index, at.blends, at.signed, self.ref_points,
                                 at.pairs.normals, system.D, r, w)
        system.add(g, upper=blocks)
        return float(np.sum(cost))


@register("depth")
def build(problem: Problem) -> DepthTerm:
    return DepthTerm(problem.ref_points, problem.params.robust, problem.params.robust_scale_m)
