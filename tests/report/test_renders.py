"""Renders of live PLYs: the fused colour where the PLY has it."""
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.ply import vertex_table, write_ply
from surfelwarp.report.renders import render_live

INTR = Intrinsics(100.0, 100.0, 39.5, 29.5, 80, 60)


def two_disks(tmp_path, colour):
    position = np.array([[-0.15, 0.0, 1.0], [0.15, 0.0, 1.0]], np.float32)
    normal = np.tile(np.float32([0.0, 0.0, -1.0]), (2, 1))
    rgb = np.array([[200, 30, 10], [20, 40, 220]], np.float32) if colour else None
    path = tmp_path / "live.ply"
    write_ply(path, vertex_table(position, normal, position, np.full(2, 0.05, np.float32), np.ones(2, np.float32),
                                 np.arange(2, dtype=np.uint32), rgb))
    return path


def test_colour_render_shows_each_surfel_in_its_colour(gl, tmp_path):
    image = render_live(two_disks(tmp_path, True), INTR, colour=True)
    left, right = image[30, 40 - 15], image[30, 40 + 15]     # the disk centres at 1 m: 15 px off
    np.testing.assert_allclose(left, np.array([200, 30, 10]) / 255, atol=1e-6)
    np.testing.assert_allclose(right, np.array([20, 40, 220]) / 255, atol=1e-6)
    assert (image[2, 40] == 1.0).all()                        # nothing drawn there: white


def test_without_colour_it_is_the_normal_map(gl, tmp_path):
    image = render_live(two_disks(tmp_path, False), INTR, colour=True)
    np.testing.assert_allclose(image[30, 25], [0.5, 0.5, 1.0], atol=1e-3)   # facing the camera
