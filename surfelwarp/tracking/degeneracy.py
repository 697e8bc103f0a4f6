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

from surfelwarp.geometry.se3 import se3_exp, se3_log, skew, solve_measured


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
        return self.frame.to_world(-solve_measured(0.5 * (self.H + self.H.T), g, min_eigen_ratio))


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
    m = np.zeros(MOMENTS)
    _moments(p, n, w, r, m, np.empty(6))
    return information_from(m)


# Raw sums of point-to-plane pairs about the world origin, from which the information about
# the pairs' centroid follows (information_from): one pass over the pairs, which the rigid
# ICP's pairing kernel makes as it pairs. H0 (36, upper triangle), g0 (6), sum w, sum w p (3),
# sum w |p|^2; J0 = (p x n, n).
MOMENTS = 47


@numba.njit(cache=True, inline="always")
def add_pair(m, J, p0, p1, p2, n0, n1, n2, w, r):
    """Adds one pair to the raw sums m (J: six floats of scratch)."""
    J[0], J[1], J[2] = p1 * n2 - p2 * n1, p2 * n0 - p0 * n2, p0 * n1 - p1 * n0
    J[3], J[4], J[5] = n0, n1, n2
    for a in range(6):
        wa = w * J[a]
        m[36 + a] += wa * r
        for b in range(a, 6):
            m[6 * a + b] += wa * J[b]
    m[42] += w
    m[43] += w * p0
    m[44] += w * p1
    m[45] += w * p2
    m[46] += w * (p0 * p0 + p1 * p1 + p2 * p2)


@numba.njit(cache=True, nogil=True)
def _moments(p, n, w, r, m, J):
    for i in range(p.shape[1]):
        add_pair(m, J, p[0, i], p[1, i], p[2, i], n[0, i], n[1, i], n[2, i], w[i], r[i])


def information_from(m: np.ndarray) -> tuple[RigidInformation, np.ndarray]:
    """The information and gradient of raw sums m about the pairs' weighted centroid c, the
    rotation scaled by their weighted RMS distance L from it (at least 1 mm): the rows about c
    are J = A J0 with A = ((I / L, -[c]x / L), (0, I)), since (p - c) x n = p x n - c x n."""
    total = max(m[42], 1e-12)
    centre = m[43:46] / total
    length = max(float(np.sqrt(max(m[46] / total - centre @ centre, 0.0))), 1e-3)
    H0 = np.triu(m[:36].reshape(6, 6))
    H0 = H0 + np.triu(H0, 1).T
    A = np.eye(6)
    A[:3, :3] /= length
    A[:3, 3:] = -skew(centre) / length
    return RigidInformation(A @ H0 @ A.T, Parametrisation(centre, length)), A @ m[36:42]
