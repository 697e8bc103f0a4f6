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
        return cls._with_rows(points, normals, weights)[0]

    @classmethod
    def _with_rows(cls, points, normals, weights) -> tuple["RigidInformation", np.ndarray]:
        """of_pairs, and the pairs' Jacobian rows (6, M) in its parametrisation."""
        p, n = np.asarray(points, np.float64), np.asarray(normals, np.float64)
        w = np.ones(p.shape[1]) if weights is None else np.asarray(weights, np.float64)
        total = max(float(w.sum()), 1e-12)
        centre = p @ w / total
        q = p - centre[:, None]
        length = max(float(np.sqrt(np.einsum("ij,ij,j->", q, q, w) / total)), 1e-3)
        J = _rows(q, n, length)
        return cls((J * w) @ J.T, Parametrisation(centre, length)), J

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


def _rows(q: np.ndarray, n: np.ndarray, length: float) -> np.ndarray:
    """(6, M) d(n . p) / d(L omega, v_c) for p = c + q turned about c: ((q x n) / L, n)."""
    J = np.empty((6, q.shape[1]))
    J[0] = (q[1] * n[2] - q[2] * n[1]) / length
    J[1] = (q[2] * n[0] - q[0] * n[2]) / length
    J[2] = (q[0] * n[1] - q[1] * n[0]) / length
    J[3:] = n
    return J


def step(points: np.ndarray, normals: np.ndarray, residuals: np.ndarray, weights: np.ndarray | None,
         min_eigen_ratio: float) -> tuple[np.ndarray, RigidInformation]:
    """The weighted point-to-plane Gauss-Newton twist (omega, v) for exp(xi) p, remapped to
    the directions the pairs constrain; and the pairs' information."""
    info, J = RigidInformation._with_rows(points, normals, weights)
    r = np.asarray(residuals, np.float64)
    g = J @ (r if weights is None else np.asarray(weights, np.float64) * r)
    return info.solve(g, min_eigen_ratio), info
