"""The sparse feature term: sum_f w_f rho(|W(r_f) - T q_f|_A), colour features put on the model.

r_f is where the feature was on the reference model (tracking/features.py), q_f where the
current frame sees it (camera frame; T the solve's camera pose). The distance is measured in
the frame of the surface normal n at q_f: |d|_A^2 = share (n.d)^2 + |d - (n.d) n|^2. Along the
normal the depth term is far better (it sums every pixel; a feature's point is one noisy depth
sample), so `feature_normal_share` (< 1) leaves that direction mostly to it; along the surface
depth sees nothing and the features decide. Three point-to-plane rows a feature (n scaled by
sqrt(share), two tangents), each with the data term's Jacobian for its axis, summed into one
product before the feature's node pairs (assembly.sparse_point_blocks with three rows a
correspondence). rho is Huber's: a wrong match that got through pulls with a bounded force.
"""
from __future__ import annotations

import numpy as np

from surfelwarp.geometry.dual_quaternion import _components, apply_components
from surfelwarp.tracking.assembly import NormalEquations, sparse_point_blocks
from surfelwarp.tracking.association import rigid_components
from surfelwarp.tracking.features import AnchoredMatches, pixel_values
from surfelwarp.tracking.terms import BaseTerm, Iterate, Problem, register, robust


def normal_frames(normals: np.ndarray, share: float) -> np.ndarray:
    """(3, n, 3) per feature: its normal scaled by sqrt(share) and two unit tangents; where the
    normal is unknown (zero), the three axes (an ordinary distance)."""
    n = np.asarray(normals, np.float64)
    length = np.linalg.norm(n, axis=1)
    known = length > 0.5
    n = np.where(known[:, None], n / np.maximum(length, 1e-12)[:, None], [0.0, 0.0, 1.0])
    # a helper axis far from the normal, then Gram-Schmidt
    helper = np.where((np.abs(n[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    scale = np.where(known, np.sqrt(share), 1.0)[:, None]
    return np.stack([scale * n, t1, t2])


class FeatureTerm(BaseTerm):
    def __init__(self, matches: AnchoredMatches, ref_points: np.ndarray, T_camera_to_world: np.ndarray,
                 weight: float, huber_m: float, target_normals: np.ndarray, normal_share: float):
        self.index, self.huber_m = np.asarray(matches.index, np.int64), huber_m
        self.weight = weight * np.asarray(matches.weights, np.float64)
        self.own = np.ascontiguousarray(np.asarray(matches.ref_points, np.float64).T)       # (3, n)
        # point_blocks reads reference points by surfel: the features' points in their surfels' columns
        self.points = np.array(ref_points, np.float64)
        self.points[:, self.index] = self.own
        T = np.asarray(T_camera_to_world, np.float64)
        self.target = np.array(rigid_components(T[:3, :3], T[:3, 3], np.asarray(matches.target_points, np.float64).T))
        self.axes = normal_frames(np.asarray(target_normals, np.float64) @ T[:3, :3].T, normal_share)   # (3, n, 3)

    def residuals(self, at: Iterate) -> np.ndarray:
        """(3, n): the live feature points minus their targets along each feature's axes."""
        blend = _components(np.take(at.blends, self.index, axis=0))
        live, _ = apply_components(blend, list(self.own))
        return np.einsum("kni,in->kn", self.axes, np.array(live) - self.target)

    def energy(self, at: Iterate) -> float:
        cost, _ = robust(np.linalg.norm(self.residuals(at), axis=0), "huber", self.huber_m)
        return float(np.sum(self.weight * cost))

    def linearize(self, at: Iterate, system: NormalEquations) -> float:
        r = self.residuals(at)
        cost, w = robust(np.linalg.norm(r, axis=0), "huber", self.huber_m)
        slots, blocks, g = sparse_point_blocks(system.pattern, self.index, at.blends, at.signed, self.points,
                                               self.axes, system.D, r, self.weight * w)
        system.add(g, upper=blocks, slots=slots)
        return float(np.sum(self.weight * cost))


@register("features")
def build(problem: Problem) -> FeatureTerm | None:
    p, matches = problem.params, problem.matches
    if matches is None or len(matches) == 0 or p.feature_weight <= 0:
        return None
    # The depth normal at each target's pixel (camera frame; zero where there is none).
    pixels = problem.intrinsics.project(np.asarray(matches.target_points, np.float64))
    normals = pixel_values(pixels, np.asarray(problem.depth_normal_map)) * \
        pixel_values(pixels, np.asarray(problem.depth_valid))[:, None]
    return FeatureTerm(matches, problem.ref_points, problem.T_camera_to_world, p.feature_weight,
                       p.feature_huber_m, normals, p.feature_normal_share)
