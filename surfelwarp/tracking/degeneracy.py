"""Rigid motion only along the directions the data constrains (Zhang, Kaess & Singh, ICRA 2016).

Point-to-plane pairs constrain a rigid motion through J = ((p - c) x n, n) per pair: a lone
plane leaves both translations along it and the turn about its normal free, a cylinder the
slide along its axis. Anything that pushes along such a direction (deforming parts, noise)
moves the solution there unopposed, frame after frame. The 6x6 information H = sum w J J^T
tells the free directions apart: its eigenvectors with eigenvalues below a share of the
largest are degenerate, and a step keeps only its components along the others ("solution
remapping": x <- V_u V_u^T x, V_u the well-conditioned eigenvectors).

Eigenvalues compare only in one parametrisation: twists are taken about the pairs' weighted
centroid c, with the rotation scaled by their RMS distance L from it, so that a turn and a
shift that move the points by the same distance weigh the same.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from surfelwarp.geometry.se3 import se3_exp, se3_log, skew


@dataclass(frozen=True)
class Parametrisation:
    """World twists (omega, v) about the origin <-> local ones (L omega, v_c) about `centre`."""
    centre: np.ndarray     # (3,) world
    length_m: float        # L

    def to_local(self, xi: np.ndarray) -> np.ndarray:
        omega, v = np.asarray(xi[:3], np.float64), np.asarray(xi[3:], np.float64)
        return np.concatenate([self.length_m * omega, v + np.cross(omega, self.centre)])

    def to_world(self, x: np.ndarray) -> np.ndarray:
        omega = np.asarray(x[:3], np.float64) / self.length_m
        return np.concatenate([omega, np.asarray(x[3:], np.float64) - np.cross(omega, self.centre)])

    def from_twist_about(self, point: np.ndarray) -> np.ndarray:
        """(6, 6) M with M zeta = the local twist of zeta = (omega, v) about `point`."""
        M = np.eye(6)
        M[:3, :3] *= self.length_m
        M[3:, :3] = -skew(self.centre - np.asarray(point, np.float64))
        return M


@dataclass(frozen=True)
class RigidInformation:
    """sum w J J^T of point-to-plane pairs in a Parametrisation (about their centroid)."""
    H: np.ndarray          # (6, 6)
    frame: Parametrisation

    @classmethod
    def of_pairs(cls, points: np.ndarray, normals: np.ndarray, weights: np.ndarray | None = None
                 ) -> "RigidInformation":
        """From (3, M) world points and normals (components), weights (M,) or None."""
        return _information(points, normals, weights, None)[0]

    def ratios(self) -> tuple[np.ndarray, np.ndarray]:
        """(6,) eigenvalues over the largest (ascending; all 0 without information) and the
        eigenvectors (6, 6) as columns."""
        lam, V = np.linalg.eigh(0.5 * (self.H + self.H.T))
        return (lam / lam[-1] if lam[-1] > 0 else np.zeros(6)), V

    def held(self, min_eigen_ratio: float) -> "HeldDirections":
        """The directions with an eigenvalue ratio at most min_eigen_ratio."""
        ratio, V = self.ratios()
        return HeldDirections(self.frame, V[:, ratio <= min_eigen_ratio])

    def solve(self, g: np.ndarray, min_eigen_ratio: float) -> np.ndarray:
        """The Gauss-Newton step -H^-1 g (g local) along the directions above min_eigen_ratio
        only, as a world twist."""
        lam, V = np.linalg.eigh(0.5 * (self.H + self.H.T))
        keep = lam > min_eigen_ratio * max(lam[-1], 0.0)
        return self.frame.to_world(-V[:, keep] @ ((V[:, keep].T @ g) / lam[keep]))


@dataclass(frozen=True)
class HeldDirections:
    """Directions (orthonormal local columns) a rigid motion must not move along."""
    frame: Parametrisation
    basis: np.ndarray      # (6, k)

    def __len__(self) -> int:
        return self.basis.shape[1]

    def project(self, T: np.ndarray) -> np.ndarray:
        """The rigid motion T (4x4, world) without its components along the held directions."""
        if not len(self):
            return np.asarray(T, np.float64)
        x = self.frame.to_local(se3_log(T))
        return se3_exp(self.frame.to_world(x - self.basis @ (self.basis.T @ x)))

    def rows(self, point: np.ndarray) -> np.ndarray:
        """(k, 6) K with K zeta = the held components of a twist zeta about `point`."""
        return self.basis.T @ self.frame.from_twist_about(point)


def _information(points, normals, weights, residuals) -> tuple[RigidInformation, np.ndarray]:
    """The pairs' information and gradient sum w r J (zero without residuals)."""
    p, n = np.ascontiguousarray(points, np.float64), np.ascontiguousarray(normals, np.float64)
    w = np.ones(p.shape[1]) if weights is None else np.ascontiguousarray(weights, np.float64)
    r = np.zeros(p.shape[1]) if residuals is None else np.ascontiguousarray(residuals, np.float64)
    H, g, centre, length = _sums(p, n, w, r)
    return RigidInformation(H, Parametrisation(centre, length)), g


@numba.njit(cache=True, nogil=True)
def _sums(p, n, w, r):
    """H = sum w J J^T and g = sum w r J of the rows J = ((q x n) / L, n), q = p - c, about the
    weighted centroid c with L the weighted RMS distance from it (at least 1 mm): the same
    sums as whole-array products, in three passes and no (6, M) rows."""
    m = p.shape[1]
    total = 0.0
    centre = np.zeros(3)
    for i in range(m):
        total += w[i]
        for a in range(3):
            centre[a] += w[i] * p[a, i]
    total = max(total, 1e-12)
    centre /= total
    spread = 0.0
    for i in range(m):
        q0, q1, q2 = p[0, i] - centre[0], p[1, i] - centre[1], p[2, i] - centre[2]
        spread += w[i] * (q0 * q0 + q1 * q1 + q2 * q2)
    length = max(np.sqrt(spread / total), 1e-3)
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.empty(6)
    for i in range(m):
        q0, q1, q2 = p[0, i] - centre[0], p[1, i] - centre[1], p[2, i] - centre[2]
        J[0] = (q1 * n[2, i] - q2 * n[1, i]) / length
        J[1] = (q2 * n[0, i] - q0 * n[2, i]) / length
        J[2] = (q0 * n[1, i] - q1 * n[0, i]) / length
        J[3], J[4], J[5] = n[0, i], n[1, i], n[2, i]
        for a in range(6):
            g[a] += w[i] * r[i] * J[a]
            for b in range(a, 6):
                H[a, b] += w[i] * J[a] * J[b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, centre, length


def step(points: np.ndarray, normals: np.ndarray, residuals: np.ndarray, weights: np.ndarray | None,
         min_eigen_ratio: float) -> tuple[np.ndarray, RigidInformation]:
    """The weighted point-to-plane Gauss-Newton twist (omega, v) for exp(xi) p, remapped to
    the directions the pairs constrain; and the pairs' information."""
    info, g = _information(points, normals, weights, residuals)
    return info.solve(g, min_eigen_ratio), info
