"""The synthetic scenes: meshes with a fixed vertex set and their motion per frame.

Scene coordinates follow the camera convention (x right, y down, z forward, metres); the
first frame's camera sits at the origin unless the scene moves the camera. Motions are
defined per frame index (fixed speed per frame), so more frames mean a longer sequence of
the same motion. Every deformation is isometric or close to it: bending of a strip (exact),
bending of thin tubes (strain = radius x curvature <= 3 %) and a mild torsion (shear <= 6 %,
i.e. <= 3 % principal stretch); the rest is rigid. The one exception is limb-wall: a 9 cm
thick limb bending 100 degrees stretches its outer side and compresses its inner side by 22 %,
as flesh does (Scene.max_strain).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from . import meshes, tangential
from .animation import SPACING_M, Animation, Scene, look_at, smoothstep, static_camera
from .meshes import rotation


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
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, static_camera)


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

    return Animation(faces, part, is_tube, positions, static_camera)


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
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, static_camera)


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

    return Animation(faces, part, np.ones(len(vertices), bool), positions, static_camera)


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
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, static_camera)


def fast_wall() -> Animation:
    """`fast`'s ball before a still textured wall 45 cm behind it: the wall holds the camera's
    pose, so the ball's 4.5 cm a frame (more than the depth pairs' 3 cm gate) is the warp
    field's to follow, not rigid ICP's."""
    ball = fast()
    wall, wall_faces = meshes.plane(3.0, 2.4, 0.025)
    vertices, faces, part = meshes.merge((wall + [0.0, 0.0, 1.45], wall_faces), (ball.positions(0), ball.faces))
    is_ball = part == 1

    def positions(i: int) -> np.ndarray:
        out = vertices.copy()
        out[is_ball] = ball.positions(i)
        return out

    return Animation(faces, part, is_ball, positions, static_camera)


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


def wall_slide() -> Animation:
    """A textured flat wall filling the view, the camera sliding along it and turning about its
    normal: depth sees a plane, which fixes only the camera's distance and tilt."""
    wall, faces = meshes.plane(3.0, 2.4, SPACING_M)
    vertices = wall + [0.0, 0.0, 1.1]

    def camera(i: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = rotation("z", np.deg2rad(0.15) * i)
        T[:3, 3] = [0.007 * i, 0.003 * i, 0.0]
        return T

    return Animation(faces, np.zeros(len(vertices), np.int16), np.zeros(len(vertices), bool), lambda i: vertices,
                     camera)


def _ramp(t: float, ease: float = 0.2) -> float:
    """0 -> 1 over t in [0, 1] at constant speed, easing in and out over `ease` of the time
    (speed 1 / (1 - ease): 1.25, against 1.57 for a cosine)."""
    t = float(np.clip(t, 0.0, 1.0))
    if t < ease:
        p = t * t / (2 * ease)
    elif t <= 1 - ease:
        p = ease / 2 + t - ease
    else:
        p = 1 - ease - (1 - t) ** 2 / (2 * ease)
    return p / (1 - ease)


def limb_wall() -> Animation:
    radius, length = 0.045, 0.35
    limb, limb_faces = meshes.capsule(radius, length, SPACING_M)
    # One flat wall and nothing else still: it constrains the camera's depth and tilt, and
    # leaves both translations along it and the turn about its normal to the limb alone.
    wall, wall_faces = meshes.plane(2.4, 1.8, 0.025)
    vertices, faces, part = meshes.merge((wall @ rotation("y", 0.1).T + [0.0, 0.0, 1.3], wall_faces),
                                         (limb, limb_faces))
    is_limb = part == 1
    s, a, b = limb[:, 1], limb[:, 0], limb[:, 2]
    s_grid = np.linspace(0.0, length, 351)
    lean = rotation("y", 0.25)                     # bending plane turned 14 deg into depth
    base = np.array([-0.12, 0.35, 0.9])            # the root's cap reaches the bottom of the image

    def positions(i: int) -> np.ndarray:
        # Bends to 100 deg at frame 40 and back by 80, curvature spread along the limb (a
        # thick limb bends with ~22 % strain on its inner and outer sides).
        u = (i % 80) / 40
        angle = np.deg2rad(100.0) * _ramp(u if u <= 1 else 2 - u)
        e1, e2 = meshes.bend_strip(s, a, s_grid, angle * s_grid / length)
        local = np.stack([e2, -e1, b], -1)         # axis to world -y, bending direction to +x
        out = vertices.copy()
        out[is_limb] = local @ lean.T + base
        return out

    return Animation(faces, part, is_limb, positions, static_camera)


def _wall(material: np.ndarray) -> np.ndarray:     # limb-wall's wall lies 1.18-1.42 m away, its limb nearer
    return material[:, 2] > 1.1


def limb_plainwall() -> Animation:        # a patterned sleeve before a white wall: the only texture moves
    return replace(limb_wall(), plain=_wall)


def plainlimb_wall() -> Animation:        # DIS's flow on the plain limb is the wall's, carried over its outline
    return replace(limb_wall(), plain=lambda material: ~_wall(material))


def free_sheet() -> Animation:
    width, height = 0.5, 0.4
    rest, faces = meshes.plane(width, height, SPACING_M)
    s, r = rest[:, 0] + width / 2, rest[:, 1]
    s_grid = np.linspace(0.0, width, 501)
    centre_line = np.zeros_like(s_grid)

    def positions(i: int) -> np.ndarray:
        # Waves travel along the sheet (0.3 m long, one wavelength per 40 frames) and nothing
        # holds it: the shape moves across the material, which depth alone cannot tell from
        # material sliding; the sheet turns slowly as a whole.
        theta = 0.45 * np.sin(2 * np.pi * (s_grid / 0.3 - i / 40)) + 0.1 * np.sin(2 * np.pi * s_grid / 0.5 + 0.7)
        ripple = 0.002 * np.sin(2 * np.pi * r / 0.2 + 0.5) * (0.7 + 0.3 * np.sin(2 * np.pi * i / 40))
        x, z = meshes.bend_strip(s, ripple, s_grid, theta)
        # The centre line's chord along x, its centroid at the origin: a free sheet has no
        # fixed point, and this keeps the material's motion smooth.
        cx, cz = meshes.bend_strip(s_grid, centre_line, s_grid, theta)
        chord = np.arctan2(cz[-1] - cz[0], cx[-1] - cx[0])
        local = np.stack([x - cx.mean(), r, z - cz.mean()], -1) @ rotation("y", chord).T
        turn = rotation("y", 0.35 * np.sin(2 * np.pi * i / 120)) @ rotation("x", 0.12 * np.sin(2 * np.pi * i / 90))
        return local @ turn.T + [0.02 * np.sin(2 * np.pi * i / 100), 0.0, 0.85]

    n = len(rest)
    return Animation(faces, np.zeros(n, np.int16), np.ones(n, bool), positions, static_camera)


def _segment(mesh: np.ndarray, start: np.ndarray, end: np.ndarray, side: np.ndarray) -> np.ndarray:
    """A capsule mesh along local +y placed from `start` towards `end`; its local x turned
    towards `side` (a continuous choice, so the part does not spin about its axis)."""
    y = (end - start) / np.linalg.norm(end - start)
    x = side - (side @ y) * y
    x /= np.linalg.norm(x)
    return mesh @ np.stack([x, y, np.cross(x, y)], -1).T + start


def _elbow(shoulder: np.ndarray, hand: np.ndarray, upper: float, fore: float, pole: np.ndarray) -> np.ndarray:
    """Two-link inverse kinematics: the elbow between shoulder and hand, bent towards `pole`."""
    d = hand - shoulder
    dist = np.linalg.norm(d)
    axis = d / dist
    along = (upper ** 2 - fore ** 2 + dist ** 2) / (2 * dist)
    out = pole - (pole @ axis) * axis
    out /= np.linalg.norm(out)
    return shoulder + along * axis + np.sqrt(max(upper ** 2 - along ** 2, 0.0)) * out


def table() -> Animation:
    # Built in a table frame (x right, y away from the camera, z up), seen by a still camera
    # above the near edge looking down at the table and the person across it.
    k = SPACING_M
    top, top_faces = meshes.plane(1.6, 1.0, 0.025)
    skirt_long, skirt_long_faces = meshes.plane(1.6, 0.05, 0.025)
    skirt_short, skirt_short_faces = meshes.plane(1.0, 0.05, 0.025)
    floor, floor_faces = meshes.plane(3.0, 2.0, 0.05)
    wall, wall_faces = meshes.plane(3.0, 1.8, 0.05)
    up = rotation("x", np.pi / 2)                  # local +y to +z
    torso, torso_faces = meshes.capsule(0.15, 0.45, k)
    torso = torso * [1.0, 1.0, 0.65]               # flatter front to back
    head, head_faces = meshes.sphere(0.095, k)
    upper, fore = 0.27, 0.25
    upper_arm, upper_faces = meshes.capsule(0.045, upper, k)
    forearm, fore_faces = meshes.capsule(0.037, fore, k)
    hand, hand_faces = meshes.sphere(0.045, k)
    side_x = rotation("x", np.pi / 2)
    parts = [
        (top, top_faces),
        (skirt_long @ side_x.T + [0.0, -0.5, -0.025], skirt_long_faces),
        (skirt_long @ side_x.T + [0.0, 0.5, -0.025], skirt_long_faces),
        (skirt_short @ (rotation("z", np.pi / 2) @ side_x).T + [-0.8, 0.0, -0.025], skirt_short_faces),
        (skirt_short @ (rotation("z", np.pi / 2) @ side_x).T + [0.8, 0.0, -0.025], skirt_short_faces),
        (np.concatenate([floor + [0.0, 0.1, -0.75], wall @ side_x.T + [0.0, 1.1, 0.15]]),
         np.concatenate([floor_faces, wall_faces + len(floor)])),
        (torso @ up.T, torso_faces),
        (head, head_faces),
        (upper_arm, upper_faces), (forearm, fore_faces), (hand, hand_faces),
        (upper_arm, upper_faces), (forearm, fore_faces), (hand, hand_faces),
    ]
    vertices, faces, part = meshes.merge(*parts)
    static = part <= 5
    hip = np.array([0.0, 0.6, -0.2])

    def positions(i: int) -> np.ndarray:
        out = vertices.copy()
        # The torso sways a little about the hips; the hands move over the table, touching
        # it at times (the left one circles, the right one reaches forward and lifts).
        sway = rotation("x", 0.04 * np.sin(2 * np.pi * i / 90)) @ rotation("y", 0.03 * np.sin(2 * np.pi * i / 70))
        body = lambda p: (p - hip) @ sway.T + hip  # noqa: E731
        out[part == 6] = body(vertices[part == 6] + [0.0, 0.6, -0.15])
        out[part == 7] = body(vertices[part == 7] + [0.0, 0.6, 0.48])
        phase = 2 * np.pi * i / 80
        hands = [np.array([-0.25 + 0.1 * np.sin(phase), 0.3 + 0.1 * np.cos(phase), 0.065 + 0.02 * np.cos(phase)]),
                 np.array([0.24 + 0.03 * np.sin(0.7 * phase), 0.25 + 0.12 * np.sin(phase + 1.0),
                           0.08 + 0.035 * np.cos(1.5 * phase)])]
        for side, hand_at, first in ((-1, hands[0], 8), (1, hands[1], 11)):
            shoulder = body(np.array([0.2 * side, 0.57, 0.33]))
            elbow = _elbow(shoulder, hand_at, upper, fore, np.array([side, 0.0, -0.3]))
            lateral = np.array([0.0, 0.0, 1.0])
            out[part == first] = _segment(vertices[part == first], shoulder, elbow, lateral)
            out[part == first + 1] = _segment(vertices[part == first + 1], elbow, hand_at, lateral)
            out[part == first + 2] = vertices[part == first + 2] + hand_at
        return out

    camera = look_at(np.array([0.0, -0.35, 1.2]), np.array([0.0, 0.35, 0.1]), np.array([0.0, 0.0, 1.0]))
    return Animation(faces, part, ~static, positions, lambda _: camera)


SCENES = {s.name: s for s in (
    Scene("sheet", "a 0.5 x 0.4 m folded cloth sheet waving from a still edge, ~0.85 m away", 90, sheet),
    Scene("tube-wall", "a bending, swinging tube (arm, 5 cm thick) in a static room corner (wall, floor, side wall)", 90, tube_wall),
    Scene("twist", "a fluted cylinder spinning and twisting about its axis (tangential motion)", 80, twist),
    Scene("touch", "two fingers, apart at first, close until they touch along their length, then open", 90, touch),
    Scene("release", "two fingers touching at first, open, close again, reopen", 90, release),
    Scene("fast", "a bumpy ball moving up to ~4.5 cm and turning ~3 deg per frame", 60, fast),
    Scene("fast-wall", "fast's ball before a still textured wall (the wall holds the camera; the ball moves "
          "up to 4.5 cm a frame, past the depth pairs' reach)", 60, fast_wall),
    Scene("orbit", "the camera circles 100 deg around a static still life (pedestal, ball, ring, rod)", 100, orbit),
    Scene("wall-slide", "the camera slides 28 cm along a textured flat wall that fills the view and turns 6 deg "
          "about its normal (depth fixes only distance and tilt: colour only)", 40, wall_slide),
    Scene("limb-wall", "a 9 cm thick limb bending 100 deg and back in front of a lone flat wall, still camera", 40,
          limb_wall, max_strain=0.23),
    Scene("limb-plainwall", "limb-wall, its wall plain (no texture)", 40, limb_plainwall, max_strain=0.23),
    Scene("plainlimb-wall", "limb-wall, its limb plain (no texture)", 40, plainlimb_wall, max_strain=0.23),
    Scene("free-sheet", "a free sheet (no still edge) turning slowly, waves travelling across it", 40, free_sheet),
    Scene("table", "a person at a table moving both arms over it (touching it), still camera overhead", 90, table),
    Scene("twist-limb", "a smooth limb (8 cm thick) before a wall turning about its own axis and sliding along it "
          "(tangential motion: colour only)", 60, tangential.twist_limb),
    Scene("roll", "a smooth textured ball rolling to and fro on a table top (its turn is tangential motion)", 60,
          tangential.roll),
)}
