"""Pinhole camera in the OpenCV convention (x right, y down, z forward).

Pixel (0, 0) is the centre of the top-left pixel: u = fx*x/z + cx, v = fy*y/z + cy.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 0
    height: int = 0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def focal_px(self) -> float:
        return 0.5 * (self.fx + self.fy)

    def with_size(self, width: int, height: int) -> "Intrinsics":
        return replace(self, width=int(width), height=int(height))

    def supersampled(self, factor: int) -> "Intrinsics":
        """The same camera on a grid `factor` times finer; pixel centres stay consistent."""
        offset = 0.5 * (factor - 1)
        return Intrinsics(self.fx * factor, self.fy * factor, self.cx * factor + offset,
                          self.cy * factor + offset, self.width * factor, self.height * factor)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) pixel coordinates (u, v)."""
        z = points[:, 2]
        return np.stack([self.fx * points[:, 0] / z + self.cx, self.fy * points[:, 1] / z + self.cy], axis=1)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) depth in metres -> (H, W, 3) vertex map; zero depth gives the zero vector."""
        h, w = depth.shape
        u = (np.arange(w, dtype=np.float32) - self.cx) / self.fx
        v = (np.arange(h, dtype=np.float32) - self.cy) / self.fy
        return np.stack([depth * u[None, :], depth * v[:, None], depth], axis=-1).astype(np.float32)


# Kinect axial noise sigma(z) = a + b (z - z0)^2 metres (Nguyen, Izadi & Lovell 2012): a, b, z0.
KINECT_AXIAL_NOISE = (0.0012, 0.0019, 0.4)


def axial_noise_sigma_m(depth_m, coeffs: tuple[float, ...] = KINECT_AXIAL_NOISE):
    """The depth sensor's axial noise standard deviation at each depth (keeps float32 float32)."""
    a, b, z0 = coeffs
    z = np.asarray(depth_m)
    return a + b * (z - z0) ** 2
