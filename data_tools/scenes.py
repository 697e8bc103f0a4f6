"""The synthetic scenes: meshes with a fixed vertex set and their motion per frame.

Scene coordinates follow the camera convention (x right, y down, z forward, metres); the
first frame's camera sits at the origin unless the scene moves the camera. Motions are
defined per frame index (fixed speed per frame), so more frames mean a longer sequence of
the same motion. Every deformation is isometric or close to it: bending of a strip (exact),
bending of thin tubes (strain = radius x curvature <= 3 %) and a mild torsion (shear <= 6 %,
i.e. <= 3 % principal stretch); the rest is rigid.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import meshes
from .meshes import rotation

SPACING_M = 0.005     # vertex spacing of curved surfaces; flat walls are exact with large triangles


@dataclass(frozen=True)
class Animation:
    faces: np.ndarray                         # (F, 3) int32
    part: np.ndarray                          # (V,) int16, which rigid/deforming piece
    moving: np.ndarray                        # (V,) bool, True where the vertex moves in the scene
    positions: Callable[[int], np.ndarray]    # frame -> (V, 3) scene-frame vertices
    camera: Callable[[int], np.ndarray]       # frame -> 4x4 camera-to-scene


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    default_frames: int
    build: Callable[[], Animation]


def _static_camera(_: int) -> np.ndarray:
    return np.eye(4)


def smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def sheet() -> Animation:
    width, height = 0.5, 0.4
    rest, faces = meshes.plane(width, height, SPACING_M)
    s, r = rest[:, 0] + width / 2, rest[:, 1]          # s: arc length from the pole
    s_grid = np.linspace(0.0, width, 501)
    envelope = smoothstep(s_grid / 0.15)                 # the pole edge stays still
    pole = np.array([-0.22, 0.0, 0.85])
    yaw = rotation("y", -0.2)

    def positions(i: int) -> np.ndarray:
        # Standing waves over a folded rest shape: material points move mostly along the
        # sheet's normal, and the sheet is never flat. A travelling wave, or a sheet passing
        # through flat, moves material along the surface in ways no depth-only tracker observes.
        theta = (0.12 * np.sin(2 * np.pi * i / 90)
                 + envelope * (0.5 * np.sin(2 * np.pi * s_grid / 0.35)
                               + 0.25 * np.sin(2 * np.pi * s_grid / 0.25 + 1.0) * np.sin(2 * np.pi * i / 50)))
        # Ripples across the folds (2 mm): without them the sheet is a ruled surface, and
        # sliding along its rulings would be invisible to depth. Their strain is the ripple
        # height times the fold curvature, kept near 3 %.
        ripple = 0.002 * smoothstep(s / 0.15) * np.sin(2 * np.pi * r / 0.2 + 0.5) * (0.7 + 0.3 * np.sin(2 * np.pi * i / 40))
        x, z = meshes.bend_strip(s, ripple, s_grid, theta)
        return np.stack([x, r, z], -1) @ yaw.T + pole

    n = len(rest)
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, _static_camera)


def tube_wall() -> Animation:
    radius, length = 0.025, 0.35
    tube, tube_faces = meshes.capsule(radius, length, SPACING_M)
    # A room corner (back wall, floor, side wall): a lone flat wall would leave the camera free
    # to slide along it, which depth cannot see.
    wall, wall_faces = meshes.plane(2.4, 1.8, 0.025)
    floor, floor_faces = meshes.plane(2.4, 1.4, 0.025)
    side, side_faces = meshes.plane(0.8, 1.8, 0.025)
    vertices, faces, part = meshes.merge(
        (wall @ rotation("y", 0.15).T + [0.0, 0.0, 1.3], wall_faces),
        (floor @ rotation("x", np.pi / 2).T + [0.0, 0.36, 0.9], floor_faces),
        (side @ rotation("y", 0.9).T + [-0.55, 0.0, 1.05], side_faces),
        (tube, tube_faces))
    is_tube = part == 3
    # Local tube frame: axis s along +y (up in the image is world -y), bending towards local +x.
    s, a, b = tube[:, 1], tube[:, 0], tube[:, 2]
    s_grid = np.linspace(0.0, length, 351)
    lean = rotation("y", 0.5)                      # bending plane turned 30 deg into depth
    base = np.array([0.05, 0.28, 0.95])

    def positions(i: int) -> np.ndarray:
        kappa = 1.2 * np.sin(2 * np.pi * i / 80)
        e1, e2 = meshes.bend_strip(s, a, s_grid, kappa * s_grid)
        local = np.stack([e2, -e1, b], -1)         # axis to world -y, bending direction to +x
        swing = rotation("z", 0.25 * np.sin(2 * np.pi * i / 100 + 0.5))
        out = vertices.copy()
        out[is_tube] = local @ (swing @ lean).T + base
        return out

    return Animation(faces, part, is_tube, positions, _static_camera)


def twist() -> Animation:
    radius, height = 0.06, 0.32
    rest, faces = meshes.rounded_cylinder(radius, height, 0.01, SPACING_M)
    phi = np.arctan2(-rest[:, 2], rest[:, 0])
    rest = rest * np.stack([1 + 0.06 * np.cos(6 * phi), np.ones(len(rest)), 1 + 0.06 * np.cos(6 * phi)], -1)
    y = rest[:, 1]
    place = rotation("x", 0.35)                    # top tilted towards the camera
    centre = np.array([0.0, 0.0, 0.9])

    def positions(i: int) -> np.ndarray:
        spin = 0.6 * np.sin(2 * np.pi * i / 70)
        torsion = 0.15 * np.sin(2 * np.pi * i / 45)
        alpha = spin + torsion * (2 * y / height - 1)
        c, sn = np.cos(alpha), np.sin(alpha)
        x = c * rest[:, 0] + sn * rest[:, 2]
        z = -sn * rest[:, 0] + c * rest[:, 2]
        local = np.stack([x, -(y - height / 2), z], -1)
        return local @ place.T + centre

    n = len(rest)
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, _static_camera)


def _fingers(opening: Callable[[int], float]) -> Animation:
    radius, length = 0.025, 0.2
    finger, finger_faces = meshes.capsule(radius, length, SPACING_M)
    vertices, faces, part = meshes.merge((finger, finger_faces), (finger, finger_faces))
    left = part == 0
    place = rotation("y", 0.3)
    base = np.array([0.0, 0.1, 0.85])

    def positions(i: int) -> np.ndarray:
        h = opening(i)
        angle, gap = 0.2 * h, 0.02 * h
        out = np.empty_like(vertices)
        for side, mask in ((-1, left), (1, ~left)):
            local = finger @ rotation("z", -side * angle).T + [side * (radius + gap), 0.0, 0.0]
            out[mask] = local
        out[:, 1] *= -1                            # fingers point up in the image
        wobble = rotation("x", 0.12 * np.sin(2 * np.pi * i / 75))
        return out @ (place @ wobble).T + base

    return Animation(faces, part, np.ones(len(vertices), bool), positions, _static_camera)


def _open_fraction(x: float) -> float:
    """0 (touching) for a while around x = 0.5 modulo 1, smoothly up to 1 (open) at x = 0."""
    return float(smoothstep((np.cos(np.pi * x) ** 2 - 0.15) / 0.85))


def touch() -> Animation:
    return _fingers(lambda i: _open_fraction(i / 60))


def release() -> Animation:
    return _fingers(lambda i: _open_fraction(i / 60 + 0.5))


def fast() -> Animation:
    rest, faces = meshes.sphere(0.075, 0.004)
    d = rest / np.linalg.norm(rest, axis=1, keepdims=True)
    bumps = 1 + 0.12 * np.sin(3 * d[:, 0] + 0.3) * np.sin(2 * d[:, 1] + 0.5) + 0.08 * np.cos(4 * d[:, 2])
    rest = rest * bumps[:, None]
    w = 0.16

    def positions(i: int) -> np.ndarray:
        centre = np.array([0.25 * np.sin(w * i), 0.05 * np.sin(2 * w * i), 1.0 + 0.08 * np.sin(w * i + 1.0)])
        # The turn swings back and forth, so a template seen at frame 0 stays in view.
        R = rotation("y", 0.45 * np.sin(0.7 * w * i)) @ rotation("x", 0.2 * np.sin(1.3 * w * i + 0.4))
        return rest @ R.T + centre

    n = len(rest)
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, _static_camera)


def orbit() -> Animation:
    target = np.array([0.0, 0.0, 0.85])
    k = 1.5                                        # the still life is ~0.3 m across
    up = rotation("x", np.pi)                      # local +y (revolve axis) to world -y
    pedestal, pf = meshes.rounded_cylinder(0.1 * k, 0.08 * k, 0.01 * k, SPACING_M)
    ball, bf = meshes.sphere(0.06 * k, SPACING_M)
    ring, rf = meshes.torus(0.06 * k, 0.018 * k, SPACING_M)
    rod, cf = meshes.capsule(0.015 * k, 0.12 * k, SPACING_M)
    parts = [
        (pedestal @ up.T + k * np.array([0.0, 0.12, 0.0]), pf),
        (ball + k * np.array([-0.035, -0.02, 0.0]), bf),
        (ring @ rotation("z", np.pi / 2).T + k * np.array([0.06, -0.038, 0.0]), rf),
        (rod @ (rotation("y", 0.6) @ rotation("z", np.pi / 2)).T + k * np.array([0.05, 0.025, -0.06]), cf),
    ]
    vertices, faces, part = meshes.merge(*[(v + target, f) for v, f in parts])
    distance = target[2]

    def camera(i: int) -> np.ndarray:
        azimuth = np.deg2rad(1.0) * i
        elevation = 0.25 * (1 - np.cos(2 * np.pi * i / 100)) / 2
        R = rotation("y", azimuth) @ rotation("x", -elevation)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, target - distance * R[:, 2]
        return T

    return Animation(faces, part, np.zeros(len(vertices), bool), lambda i: vertices, camera)


SCENES = {s.name: s for s in (
    Scene("sheet", "a 0.5 x 0.4 m folded cloth sheet waving from a still edge, ~0.85 m away", 90, sheet),
    Scene("tube-wall", "a bending, swinging tube (arm, 5 cm thick) in a static room corner (wall, floor, side wall)", 90, tube_wall),
    Scene("twist", "a fluted cylinder spinning and twisting about its axis (tangential motion)", 80, twist),
    Scene("touch", "two fingers, apart at first, close until they touch along their length, then open", 90, touch),
    Scene("release", "two fingers touching at first, open, close again, reopen", 90, release),
    Scene("fast", "a bumpy ball moving up to ~4.5 cm and turning ~3 deg per frame", 60, fast),
    Scene("orbit", "the camera circles 100 deg around a static still life (pedestal, ball, ring, rod)", 100, orbit),
)}
