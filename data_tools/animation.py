"""What a synthetic scene is: a mesh with a fixed vertex set, its motion per frame, the camera."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

SPACING_M = 0.005     # vertex spacing of curved surfaces; flat walls are exact with large triangles


@dataclass(frozen=True)
class Animation:
    faces: np.ndarray                         # (F, 3) int32
    part: np.ndarray                          # (V,) int16, which rigid/deforming piece
    moving: np.ndarray                        # (V,) bool, True where the vertex moves in the scene
    positions: Callable[[int], np.ndarray]    # frame -> (V, 3) scene-frame vertices
    camera: Callable[[int], np.ndarray]       # frame -> 4x4 camera-to-scene
    # material points (N, 3) -> True where the surface has no texture (texture.shade); None: none
    plain: Callable[[np.ndarray], np.ndarray] | None = None


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    default_frames: int
    build: Callable[[], Animation]
    max_strain: float = 0.035     # largest edge strain of the motion (0.035: near isometric)


def static_camera(_: int) -> np.ndarray:
    return np.eye(4)


def smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """4x4 camera-to-scene of a camera at `eye` looking at `target`, image up along `up`."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.stack([x, np.cross(z, x), z], -1), eye
    return T
