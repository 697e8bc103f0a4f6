"""Scenes whose motion runs along the surface, which depth cannot see and colour can."""
from __future__ import annotations

import numpy as np

from . import meshes
from .animation import SPACING_M, Animation, look_at, static_camera
from .meshes import rotation


def _room_corner() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A back wall, floor and side wall about 1.3 m away: still surface on three axes."""
    wall, wall_faces = meshes.plane(2.4, 1.8, 0.025)
    floor, floor_faces = meshes.plane(2.4, 1.4, 0.025)
    side, side_faces = meshes.plane(0.8, 1.8, 0.025)
    return meshes.merge((wall @ rotation("y", 0.15).T + [0.0, 0.0, 1.3], wall_faces),
                        (floor @ rotation("x", np.pi / 2).T + [0.0, 0.36, 0.9], floor_faces),
                        (side @ rotation("y", 0.9).T + [-0.55, 0.0, 1.05], side_faces))


def twist_limb() -> Animation:
    radius, length = 0.04, 0.3
    limb, limb_faces = meshes.capsule(radius, length, SPACING_M)
    room, room_faces, room_part = _room_corner()
    vertices, faces, part = meshes.merge((room, room_faces), (limb, limb_faces))
    part = np.concatenate([room_part, np.full(len(limb), 3)]).astype(np.int16)
    is_limb = part == 3
    y = limb[:, 1]
    place = rotation("z", 0.35) @ rotation("x", 0.3)        # leaning, its top towards the camera
    centre = np.array([0.05, 0.0, 0.85])

    def positions(i: int) -> np.ndarray:
        # It turns about its own axis by up to 45 deg (surface speed up to ~3.5 mm a frame),
        # twists by up to 17 deg end to end, and slides 3 cm along the axis: a smooth cylinder
        # looks the same throughout.
        spin = 0.8 * np.sin(2 * np.pi * i / 60)
        alpha = spin + 0.15 * np.sin(2 * np.pi * i / 40) * (2 * y / length - 1)
        c, s = np.cos(alpha), np.sin(alpha)
        local = np.stack([c * limb[:, 0] + s * limb[:, 2], y - length / 2 + 0.03 * np.sin(2 * np.pi * i / 50),
                          -s * limb[:, 0] + c * limb[:, 2]], -1)
        local[:, 1] *= -1                          # the axis points up in the image
        out = vertices.copy()
        out[is_limb] = local @ place.T + centre
        return out

    return Animation(faces, part, is_limb, positions, static_camera)


def roll() -> Animation:
    # Built in a table frame (x right, y away from the camera, z up).
    radius = 0.07
    top, top_faces = meshes.plane(1.2, 0.8, 0.025)
    ball, ball_faces = meshes.sphere(radius, SPACING_M)
    vertices, faces, part = meshes.merge((top, top_faces), (ball, ball_faces))
    is_ball = part == 1

    def positions(i: int) -> np.ndarray:
        # Rolling without slipping: the turn about the axis across the motion is the distance
        # over the radius (the top moves up to ~1.2 cm a frame), which a smooth sphere hides from depth.
        x = 0.09 * np.sin(2 * np.pi * i / 100)
        y = 0.025 * np.sin(2 * np.pi * i / 75)
        R = rotation("y", x / radius) @ rotation("x", -y / radius)
        out = vertices.copy()
        out[is_ball] = ball @ R.T + [x, y, radius]
        return out

    camera = look_at(np.array([0.0, -0.55, 0.55]), np.array([0.0, 0.05, 0.05]), np.array([0.0, 0.0, 1.0]))
    return Animation(faces, part, is_ball, positions, lambda _: camera)
