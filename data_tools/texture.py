"""Colour of the synthetic scenes: a texture bound to the material, Lambertian shading, 8-bit noise.

The albedo is a function of the material point (a vertex's position in the scene's first frame,
interpolated over the triangles), so the texture moves with the surface as paint would; it is
value noise at two scales (2 and 7 cm cells), blobs and corners that SIFT and ORB find. The
light is a lamp beside the camera (fixed in the camera frame: shading changes as a surface turns
or the camera moves) or, with `synth --light room`, that lamp left where it stood beside the first
frame's camera (fixed in the room: a still surface keeps its shading however the camera moves).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

BACKGROUND_RGB = (0.25, 0.25, 0.27)          # where no surface is drawn (depth 0)
LIGHT_DIRECTION = np.array([-0.35, -0.5, -1.0]) / np.linalg.norm([-0.35, -0.5, -1.0])   # towards the lamp
LIGHTS = ("camera", "room")
AMBIENT = 0.35
CELLS_M = (0.02, 0.07)
NOISE_LEVELS = 2.0                           # sigma of the 8-bit sensor noise
PLAIN_ALBEDO = 0.6                           # a surface without texture (a white wall, a plain sleeve)


def _hash(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """(N, 3) values in [0, 1) for integer lattice points, one per colour channel (three 21-bit
    slices of one 64-bit mixing hash; no table)."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) ^ iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ iz.astype(np.uint64) * np.uint64(0x165667B19E3779F9) ^ np.uint64((seed * 0x27D4EB2F165667C5 + 1) % (1 << 64)))
        h ^= h >> np.uint64(31)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(29)
    mask = np.uint64((1 << 21) - 1)
    return np.stack([(h >> np.uint64(21 * c)) & mask for c in range(3)], -1).astype(np.float32) / float(1 << 21)


def value_noise(points: np.ndarray, cell_m: float, seed: int) -> np.ndarray:
    """(N, 3) smooth noise in [0, 1] at material points (N, 3): lattice values blended
    trilinearly with a smoothstep, a channel each."""
    g = np.asarray(points, np.float64) / cell_m
    base = np.floor(g)
    f = (g - base).astype(np.float32)
    f = f * f * (3 - 2 * f)
    i = base.astype(np.int64) + (1 << 20)        # non-negative for the unsigned hash
    out = np.zeros((len(g), 3), np.float32)
    for corner in range(8):
        d = [(corner >> k) & 1 for k in range(3)]
        w = np.prod(np.where(np.array(d, bool), f, 1 - f), axis=1)
        out += w[:, None] * _hash(i[:, 0] + d[0], i[:, 1] + d[1], i[:, 2] + d[2], seed)
    return out


def albedo(material: np.ndarray, seed: int = 0) -> np.ndarray:
    """(N, 3) RGB in [0.1, 0.95] at material points (N, 3) in metres."""
    rgb = 0.6 * value_noise(material, CELLS_M[0], seed) + 0.4 * value_noise(material, CELLS_M[1], seed + 1)
    # Stretch the noise's narrow middle-heavy histogram to a contrasty one.
    return np.clip(0.5 + 1.8 * (rgb - 0.5), 0.1, 0.95)


def light_direction(light: str, camera_to_world: np.ndarray, first_camera_to_world: np.ndarray) -> np.ndarray:
    """(3,) the direction towards the lamp in a frame's camera (camera_to_world): beside it
    ("camera"), or where it stood beside the first frame's camera ("room")."""
    if light not in LIGHTS:
        raise ValueError(f"light is one of {LIGHTS}, not {light!r}")
    if light == "camera":
        return LIGHT_DIRECTION
    R, R0 = (np.asarray(T, np.float64)[:3, :3] for T in (camera_to_world, first_camera_to_world))
    return R.T @ R0 @ LIGHT_DIRECTION


def shade(depth_m: np.ndarray, normal_map: np.ndarray, material_map: np.ndarray, rng: np.random.Generator | None,
          seed: int = 0, light: np.ndarray | None = None,
          plain: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of one frame: albedo x (ambient + Lambert) where depth > 0, the
    background elsewhere, plus Gaussian 8-bit noise when `rng` is given. `light`: the direction
    towards the lamp in the camera frame (light_direction; None: the lamp beside the camera).
    `plain` (material points -> bool): where the albedo is PLAIN_ALBEDO grey, not the texture."""
    h, w = depth_m.shape
    image = np.empty((h, w, 3))
    image[:] = BACKGROUND_RGB
    drawn = depth_m > 0
    lambert = np.clip(normal_map[drawn] @ (LIGHT_DIRECTION if light is None else light), 0.0, None)
    material = material_map[drawn]
    paint = albedo(material, seed)
    if plain is not None:
        paint[plain(material)] = PLAIN_ALBEDO
    image[drawn] = paint * (AMBIENT + (1 - AMBIENT) * lambert)[:, None]
    image *= 255.0
    if rng is not None:
        image += rng.normal(0.0, NOISE_LEVELS, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
