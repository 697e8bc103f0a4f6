"""Rigid camera alignment by projective point-to-plane ICP, coarse to fine (KinectFusion).

SurfelWarp (Sec. VII) aligns the depth observation rigidly to the rendered model before the
non-rigid estimation. Each observation vertex is moved to world with the current estimate,
projected into the camera the model maps were rendered from, and paired with the model surfel
at that pixel; pairs far apart or with disagreeing normals are dropped. Each iteration solves
the 6x6 normal equations of sum w (n_model . (T v_obs - v_model))^2 for a twist xi = (omega, v)
and left-composes T <- exp(xi) T, moving only along the directions the pairs constrain
(degeneracy.py): a lone wall leaves the camera where it was along the wall instead of letting
whatever else is in view push it there.

Optional per-pixel model weights w (e.g. how still the surface at that pixel has been, from
the tracker) let the parts of the scene that hold still decide the camera's motion.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, point_jacobian, se3_exp
from surfelwarp.preprocess import CameraObservation
from surfelwarp.tracking.degeneracy import MOMENTS, HeldDirections, add_pair, information_from


@dataclass(frozen=True)
class RigidParams:
    pyramid_levels: int = 3
    iterations: tuple[int, ...] = (10, 5, 4)                 # per level, coarse to fine
    distance_gate_m: tuple[float, ...] = (0.1, 0.05, 0.025)  # per level, coarse to fine
    min_normal_cos: float = 0.8                               # normals within ~37 deg
    min_correspondences: int = 100
    stop_rotation_rad: float = 5e-5                           # an increment this small ends a level
    stop_translation_m: float = 5e-5
    # Directions of the 6x6 information with an eigenvalue at most this share of the largest
    # are never moved along (degeneracy.py).
    min_eigen_ratio: float = 0.005
    # Directions up to this share are weak: moved along only if that lowers the (still-weighted)
    # median residual by weak_median_gain, i.e. if most of the view moved so, not a minority
    # starting to move. Measured: a lone plane's free directions 0.01 (Kinect noise on the
    # normals); a table's left-right 0.045 with a person's arms, 0.016 without; a spinning
    # fluted cylinder 0.027 and a turning bumpy ball 0.019, seen whole; the turn of an orbiting
    # camera about a still life of solids of revolution 0.094-0.10, which the rod and ring
    # alone see (held at 0.1, it lagged 9 mm before the majority noticed); 7-Scenes 0.16 up.
    weak_eigen_ratio: float = 0.08
    weak_median_gain: float = 0.05

    ZERO_OK = {"iterations", "min_normal_cos", "stop_rotation_rad", "stop_translation_m", "min_eigen_ratio",
               "weak_eigen_ratio", "weak_median_gain"}
    UNIT = {"min_normal_cos", "min_eigen_ratio", "weak_eigen_ratio", "weak_median_gain"}
    AT_MOST = {"pyramid_levels": 6}

    def problems(self) -> dict[str, bool]:
        return {"iterations": len(self.iterations) != self.pyramid_levels,
                "distance_gate_m": len(self.distance_gate_m) != self.pyramid_levels}


@dataclass(frozen=True)
class RigidResult:
    T_camera_to_world: np.ndarray
    iterations: int          # total over all levels
    energy: float            # mean squared point-to-plane residual at the result, m^2
    rmse_m: float
    inliers: int             # correspondences at the finest level at the result
    converged: bool
    held: HeldDirections | None = None   # directions the camera was not moved along (at the result)

    @property
    def degenerate_directions(self) -> int:
        return 0 if self.held is None else len(self.held)


@dataclass(frozen=True)
class PointPairs:
    """Point-to-point pairs (colour correspondences): observation points (n, 3) in the camera
    frame, the world points (n, 3) they should land on, and weights (n,)."""
    camera: np.ndarray
    world: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class _Level:
    # Views of the full maps at the level's stride, (h, w, 3) and (h, w): nothing is copied, the
    # kernels walk the pixels.
    obs_vertex: np.ndarray    # camera frame
    obs_normal: np.ndarray
    obs_valid: np.ndarray
    model_vertex: np.ndarray  # world; empty pixels have a zero normal
    model_normal: np.ndarray
    model_weight: np.ndarray | None   # or None: every pair weighs 1
    intrinsics: Intrinsics
    gate_m: float
    iterations: int


def halved(intrinsics: Intrinsics) -> Intrinsics:
    """Intrinsics of the map subsampled as map[::2, ::2]: coarse pixel j is fine pixel 2j."""
    return Intrinsics(intrinsics.fx / 2, intrinsics.fy / 2, intrinsics.cx / 2, intrinsics.cy / 2,
                      (intrinsics.width + 1) // 2, (intrinsics.height + 1) // 2)


def _levels(model_vertex, model_normal, model_weight, observation, model_intrinsics, params) -> list[_Level]:
    """Pyramid levels from coarse to fine."""
    mv, mn = np.asarray(model_vertex, np.float32), np.asarray(model_normal, np.float32)
    mw = None if model_weight is None else np.asarray(model_weight, np.float32)
    ov, on = np.asarray(observation.vertex_map, np.float32), np.asarray(observation.normal_map, np.float32)
    ok = np.asarray(observation.valid, np.bool_)
    intr = model_intrinsics
    levels = []
    for level in range(params.pyramid_levels):
        h, w = mv.shape[:2]
        k = params.pyramid_levels - 1 - level
        levels.append(_Level(ov, on, ok, mv, mn, mw, intr.with_size(w, h), params.distance_gate_m[k],
                             params.iterations[k]))
        mv, mn, intr = mv[::2, ::2], mn[::2, ::2], halved(intr)
        mw = None if mw is None else mw[::2, ::2]
        ov, on, ok = ov[::2, ::2], on[::2, ::2], ok[::2, ::2]
    return levels[::-1]


def _constants(level: _Level, T: np.ndarray, T_world_to_model: np.ndarray, min_normal_cos: float):
    intr, f32 = level.intrinsics, np.float32
    weights = level.model_weight if level.model_weight is not None else np.ones((1, 1), f32)
    return (level.obs_vertex, level.obs_normal, level.obs_valid, level.model_vertex, level.model_normal, weights,
            level.model_weight is not None, np.ascontiguousarray(T[:3], f32),
            np.ascontiguousarray(T_world_to_model[:3], f32),
            np.array([intr.fx, intr.fy, intr.cx, intr.cy, level.gate_m ** 2, min_normal_cos], f32))


def _associate(level: _Level, T: np.ndarray, T_world_to_model: np.ndarray, min_normal_cos: float,
               points: bool = True):
    """World observation points (3, M), model normals (3, M), residuals (M,) and weights (M,)
    or None of the gated projective pairs, in the observation's pixel order; without `points`
    the points and normals are None, not written (a median residual on tube-wall 19.5 -> 16.1
    ms)."""
    f32, n = np.float32, level.obs_valid.size
    m = n if points else 0
    out_p, out_n, r, w = np.empty((3, m), f32), np.empty((3, m), f32), np.empty(n, f32), np.empty(n, f32)
    k = _pairs(*_constants(level, T, T_world_to_model, min_normal_cos), points, out_p, out_n, r, w)
    return (out_p[:, :k] if points else None, out_n[:, :k] if points else None, r[:k],
            (w[:k] if level.model_weight is not None else None))


def _moments_of_pairs(level: _Level, T: np.ndarray, T_world_to_model: np.ndarray, min_normal_cos: float
                      ) -> tuple[np.ndarray, int, float]:
    """The raw sums of the gated projective pairs (degeneracy.MOMENTS), their number and their
    sum of squared residuals (unweighted), made as they are found: no pair is written out."""
    rows = level.obs_valid.shape[0]
    partial = np.zeros(((rows + ROWS_PER_TASK - 1) // ROWS_PER_TASK, MOMENTS + 2))
    _pair_moments(*_constants(level, T, T_world_to_model, min_normal_cos), partial)
    total = partial.sum(axis=0)
    return total[:MOMENTS], int(total[MOMENTS]), float(total[MOMENTS + 1])


ROWS_PER_TASK = 16     # observation rows per parallel task of the pairing kernels


@numba.njit(cache=True, nogil=True, inline="always")
def _pair_at(ov, on, mv, mn, T, T_wm, c, y, x):
    """The projective pair of observation pixel (y, x) if it passes the gates: (found, world
    point, model normal, residual, model pixel)."""
    fx, fy, cx, cy, gate2, min_cos = c[0], c[1], c[2], c[3], c[4], c[5]
    vx, vy, vz = ov[y, x, 0], ov[y, x, 1], ov[y, x, 2]
    p0 = T[0, 0] * vx + T[0, 1] * vy + T[0, 2] * vz + T[0, 3]
    p1 = T[1, 0] * vx + T[1, 1] * vy + T[1, 2] * vz + T[1, 3]
    p2 = T[2, 0] * vx + T[2, 1] * vy + T[2, 2] * vz + T[2, 3]
    nothing = (False, p0, p1, p2, p0, p0, p0, p0, 0, 0)
    q2 = T_wm[2, 0] * p0 + T_wm[2, 1] * p1 + T_wm[2, 2] * p2 + T_wm[2, 3]
    if not q2 > 1e-6:
        return nothing
    q0 = T_wm[0, 0] * p0 + T_wm[0, 1] * p1 + T_wm[0, 2] * p2 + T_wm[0, 3]
    q1 = T_wm[1, 0] * p0 + T_wm[1, 1] * p1 + T_wm[1, 2] * p2 + T_wm[1, 3]
    inv_z = np.float32(1.0) / q2
    u = np.rint(fx * q0 * inv_z + cx)
    v = np.rint(fy * q1 * inv_z + cy)
    if not (u >= 0 and u < mv.shape[1] and v >= 0 and v < mv.shape[0]):
        return nothing
    i, j = int(v), int(u)
    m0, m1, m2 = mn[i, j, 0], mn[i, j, 1], mn[i, j, 2]
    if not m0 * m0 + m1 * m1 + m2 * m2 > 0.25:          # an empty model pixel
        return nothing
    d0, d1, d2 = p0 - mv[i, j, 0], p1 - mv[i, j, 1], p2 - mv[i, j, 2]
    if not d0 * d0 + d1 * d1 + d2 * d2 < gate2:
        return nothing
    nx, ny, nz = on[y, x, 0], on[y, x, 1], on[y, x, 2]
    n0 = T[0, 0] * nx + T[0, 1] * ny + T[0, 2] * nz
    n1 = T[1, 0] * nx + T[1, 1] * ny + T[1, 2] * nz
    n2 = T[2, 0] * nx + T[2, 1] * ny + T[2, 2] * nz
    if not n0 * m0 + n1 * m1 + n2 * m2 > min_cos:
        return nothing
    return (True, p0, p1, p2, m0, m1, m2, m0 * d0 + m1 * d1 + m2 * d2, i, j)


@numba.njit(cache=True, nogil=True, parallel=True)
def _pairs(ov, on, ok, mv, mn, mw, weighted, T, T_wm, c, points, out_p, out_n, out_r, out_w):
    """The pairs of _associate (float32 as the maps), in the observation's pixel order: their
    count. Each task writes its pairs from its first pixel's index on, then they are closed up.
    Their points and normals only if `points`."""
    h, w = ok.shape
    tasks = (h + ROWS_PER_TASK - 1) // ROWS_PER_TASK
    counts = np.zeros(tasks, np.int64)
    for t in numba.prange(tasks):
        k = t * ROWS_PER_TASK * w
        for y in range(t * ROWS_PER_TASK, min(h, (t + 1) * ROWS_PER_TASK)):
            for x in range(w):
                if not ok[y, x]:
                    continue
                found, p0, p1, p2, m0, m1, m2, r, i, j = _pair_at(ov, on, mv, mn, T, T_wm, c, y, x)
                if not found:
                    continue
                if points:
                    out_p[0, k], out_p[1, k], out_p[2, k] = p0, p1, p2
                    out_n[0, k], out_n[1, k], out_n[2, k] = m0, m1, m2
                out_r[k] = r
                if weighted:
                    out_w[k] = mw[i, j]
                k += 1
        counts[t] = k - t * ROWS_PER_TASK * w
    k = counts[0] if tasks else 0      # the first task's pairs are in place
    for t in range(1, tasks):
        start = t * ROWS_PER_TASK * w
        for s in range(start, start + counts[t]):
            if points:
                for a in range(3):
                    out_p[a, k] = out_p[a, s]
                    out_n[a, k] = out_n[a, s]
            out_r[k] = out_r[s]
            if weighted:
                out_w[k] = out_w[s]
            k += 1
    return k


@numba.njit(cache=True, nogil=True, parallel=True)
def _pair_moments(ov, on, ok, mv, mn, mw, weighted, T, T_wm, c, partial):
    """Each task's raw sums of its pairs (degeneracy.add_pair, in float64), then their count and
    their sum of squared residuals."""
    h, w = ok.shape
    for t in numba.prange(partial.shape[0]):
        m, J = partial[t], np.empty(6)
        for y in range(t * ROWS_PER_TASK, min(h, (t + 1) * ROWS_PER_TASK)):
            for x in range(w):
                if not ok[y, x]:
                    continue
                found, p0, p1, p2, m0, m1, m2, r, i, j = _pair_at(ov, on, mv, mn, T, T_wm, c, y, x)
                if found:
                    f = np.float64
                    add_pair(m, J, f(p0), f(p1), f(p2), f(m0), f(m1), f(m2), f(mw[i, j]) if weighted else 1.0, f(r))
                    m[MOMENTS] += 1.0
                    m[MOMENTS + 1] += f(r) * f(r)


def rigid_icp(model_vertex_map: np.ndarray, model_normal_map: np.ndarray, T_model_camera_to_world: np.ndarray,
              observation: CameraObservation, T_init_camera_to_world: np.ndarray,
              params: RigidParams = RigidParams(), model_intrinsics: Intrinsics | None = None,
              model_weight_map: np.ndarray | None = None, pairs: PointPairs | None = None) -> RigidResult:
    """Camera-to-world pose of `observation` aligned to world-frame model maps.

    The model maps (H, W, 3), zero where empty, were rendered from T_model_camera_to_world with
    `model_intrinsics` (default: the observation's camera, which then needs the same size);
    model_weight_map (H, W), if given, weighs each model pixel's pairs. `pairs` (colour) then
    move the pose along the directions the depth held (along_held), and only those: where depth
    sees the motion it leads.
    """
    if len(params.iterations) != params.pyramid_levels or len(params.distance_gate_m) != params.pyramid_levels:
        raise ValueError("iterations and distance_gate_m need one entry per pyramid level")
    h, w = np.shape(model_vertex_map)[:2]
    if model_intrinsics is None:
        if (h, w) != observation.valid.shape:
            raise ValueError("model maps differ in size from the observation: pass model_intrinsics")
        model_intrinsics = observation.intrinsics
    T_init = np.asarray(T_init_camera_to_world, np.float64)
    T_world_to_model = invert(np.asarray(T_model_camera_to_world, np.float64))
    levels = _levels(model_vertex_map, model_normal_map, model_weight_map, observation, model_intrinsics, params)

    T, total, settled, info = _align(levels, T_init, T_world_to_model, params, params.min_eigen_ratio)
    held = None if info is None else info.held(params.min_eigen_ratio)
    ratio = info.ratios()[0] if info is not None else np.ones(6)
    if np.any((ratio > params.min_eigen_ratio) & (ratio <= params.weak_eigen_ratio)):
        # The same alignment holding the weak directions: from the result without its motion
        # along them, at the finest level.
        start = info.held(params.weak_eigen_ratio).project(T @ invert(T_init)) @ T_init
        T2, total2, settled2, info2 = _align(levels[-1:], start, T_world_to_model, params, params.weak_eigen_ratio)
        total += total2
        if info2 is not None and not _median_residual(levels[-1], T, T_world_to_model, params) < \
                (1 - params.weak_median_gain) * _median_residual(levels[-1], T2, T_world_to_model, params):
            T, settled, held = T2, settled2, info2.held(params.weak_eigen_ratio)

    if pairs is not None and held is not None and len(held) and len(pairs.weights):
        T = along_held(T, held, pairs)
    _, count, squares = _moments_of_pairs(levels[-1], T, T_world_to_model, params.min_normal_cos)
    if count < params.min_correspondences:
        return RigidResult(T_init, total, float("nan"), float("nan"), count, False, held)
    energy = squares / count
    return RigidResult(T, total, energy, float(np.sqrt(energy)), count, settled, held)


def along_held(T: np.ndarray, held: HeldDirections, pairs: PointPairs, iterations: int = 5,
               stop_m: float = 1e-6) -> np.ndarray:
    """T moved along the held directions only, to fit the point pairs (Gauss-Newton on
    w |exp(B a) T q - x|^2, B the held directions as world twists): a flat wall's depth fixes
    the camera's distance and tilt, the colour on it the slide along it and the turn about it."""
    B = np.stack([held.frame.to_world(b) for b in held.basis.T], 1)          # (6, k)
    q, x = np.asarray(pairs.camera, np.float64), np.asarray(pairs.world, np.float64)
    w = np.asarray(pairs.weights, np.float64)
    if len(w) < 3 or not w.sum() > 0:
        return T
    for _ in range(iterations):
        p = q @ T[:3, :3].T + T[:3, 3]
        JB = point_jacobian(p) @ B
        H = np.einsum("n,nik,nil->kl", w, JB, JB)
        g = np.einsum("n,nik,ni->k", w, JB, p - x)
        a = -np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(len(H)), g)
        T = se3_exp(B @ a) @ T
        if np.abs(B @ a).max() < stop_m:
            break
    return T


def _align(levels: list[_Level], T_init: np.ndarray, T_world_to_model: np.ndarray, params: RigidParams,
           min_eigen_ratio: float):
    """Coarse-to-fine ICP from T_init moving only along directions above min_eigen_ratio:
    (T, iterations, settled, the last step's information or None)."""
    T, total, settled, info = T_init.copy(), 0, False, None
    for level in levels:
        settled = False
        for _ in range(level.iterations):
            moments, count, _ = _moments_of_pairs(level, T, T_world_to_model, params.min_normal_cos)
            if count < params.min_correspondences:
                break
            info, g = information_from(moments)
            xi = info.solve(g, min_eigen_ratio)
            T = se3_exp(xi) @ T
            total += 1
            settled = (np.linalg.norm(xi[:3]) < params.stop_rotation_rad
                       and np.linalg.norm(xi[3:]) < params.stop_translation_m)
            if settled:
                break
    return T, total, settled, info


def _median_residual(level: _Level, T: np.ndarray, T_world_to_model: np.ndarray, params: RigidParams) -> float:
    """Median |residual| of the level's pairs at T, weighted by the model weights if any."""
    _, _, r, w = _associate(level, T, T_world_to_model, params.min_normal_cos, points=False)
    if len(r) == 0:
        return float("inf")
    a = np.abs(r.astype(np.float64))
    if w is None:
        return float(np.median(a))
    return _weighted_median(a, w.astype(np.float64))


@numba.njit(cache=True, nogil=True)
def _weighted_median(a, w):
    """The smallest a[i] at which the weights of it and all smaller values reach half the total
    (what sorting gives). In linear time: the values' histogram finds the bin holding the
    median, and only that bin is sorted (argsort of a room's 300k pairs took ~18 ms)."""
    bins = 4096
    lo, hi = a.min(), a.max()
    if not (np.isfinite(lo) and np.isfinite(hi)):     # what sorting does with them, NaN last
        order = np.argsort(a)
        cumulative = np.cumsum(w[order])
        return a[order[np.searchsorted(cumulative, 0.5 * cumulative[-1])]]
    scale = bins / (hi - lo) if hi > lo else 0.0
    weight = np.zeros(bins + 1)
    for i in range(len(a)):
        weight[int((a[i] - lo) * scale)] += w[i]
    half = 0.5 * weight.sum()
    below = 0.0
    b = 0
    while b < bins and below + weight[b] < half:
        below += weight[b]
        b += 1
    inside = np.array([i for i in range(len(a)) if int((a[i] - lo) * scale) == b])
    order = inside[np.argsort(a[inside])]
    for i in order:
        below += w[i]
        if below >= half:
            return a[i]
    return a[order[-1]]
