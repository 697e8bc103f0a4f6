"""The sparse feature term: sum_f rho(|W(r_f) - T q_f|), colour features put on the model.

r_f is where the feature was on the reference model (tracking/features.py), q_f where the
current frame sees it (camera frame; T the solve's camera pose). Point to point, three rows a
feature, each with the data term's Jacobian for a unit normal (assembly.point_blocks). rho is
Huber's on the distance: a wrong match that got through pulls with a bounded force.
"""
from __future__ import annotations

import numpy as np

from surfelwarp.geometry.dual_quaternion import _components, apply_components
from surfelwarp.tracking.assembly import NormalEquations, point_blocks
from surfelwarp.tracking.association import rigid_components
from surfelwarp.tracking.features import AnchoredMatches
from surfelwarp.tracking.terms import BaseTerm, Iterate, Problem, register, robust


class FeatureTerm(BaseTerm):
    def __init__(self, matches: AnchoredMatches, ref_points: np.ndarray, T_camera_to_world: np.ndarray,
                 weight: float, huber_m: float):
        self.index, self.huber_m = np.asarray(matches.index, np.int64), huber_m
        self.weight = weight * np.asarray(matches.weights, np.float64)
        self.own = np.ascontiguousarray(np.asarray(matches.ref_points, np.float64).T)       # (3, n)
        # point_blocks reads reference points by surfel: the features' points in their surfels' columns
        self.points = np.array(ref_points, np.float64)
        self.points[:, self.index] = self.own
        T = np.asarray(T_camera_to_world, np.float64)
        self.target = np.array(rigid_components(T[:3, :3], T[:3, 3], np.asarray(matches.target_points, np.float64).T))
        n = len(self.index)
        self.rows = np.tile(self.index, 3)
        self.normals = np.repeat(np.eye(3), n, axis=0)

    def residuals(self, at: Iterate) -> np.ndarray:
        """(3, n) live feature points minus their targets."""
        blend = _components(np.take(at.blends, self.index, axis=0))
        live, _ = apply_components(blend, list(self.own))
        return np.array(live) - self.target

    def energy(self, at: Iterate) -> float:
        cost, _ = robust(np.linalg.norm(self.residuals(at), axis=0), "huber", self.huber_m)
        return float(np.sum(self.weight * cost))

    def linearize(self, at: Iterate, system: NormalEquations) -> float:
        r = self.residuals(at)
        cost, w = robust(np.linalg.norm(r, axis=0), "huber", self.huber_m)
        blocks, g = point_blocks(system.pattern, self.rows, at.blends, at.signed, self.points, self.normals,
                                 system.D, r.reshape(-1), np.tile(self.weight * w, 3))
        system.add(g, upper=blocks)
        return float(np.sum(self.weight * cost))


@register("features")
def build(problem: Problem) -> FeatureTerm | None:
    p = problem.params
    if problem.matches is None or len(problem.matches) == 0 or p.feature_weight <= 0:
        return None
    return FeatureTerm(problem.matches, problem.ref_points, problem.T_camera_to_world, p.feature_weight,
                       p.feature_huber_m)
