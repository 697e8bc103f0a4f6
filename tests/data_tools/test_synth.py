"""Synthetic sequences: rendered depth vs analytic depth, the Kinect noise model, the scenes."""
import argparse
from dataclasses import replace

import cv2
import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from surfelwarp.data_tools import meshes, noise, synth
from surfelwarp.data_tools.render import MeshRenderer
from surfelwarp.data_tools.scenes import SCENES
from surfelwarp.errors import InputError
from surfelwarp.io.sequence import open_sequence


def rays(intr):
    u, v = np.meshgrid((np.arange(intr.width) - intr.cx) / intr.fx, (np.arange(intr.height) - intr.cy) / intr.fy)
    return np.stack([u, v, np.ones_like(u)], -1)


def plane_depth(intr, normal, point):
    return (normal @ point) / (rays(intr) @ normal)


@pytest.fixture(scope="module")
def small():
    return synth.default_intrinsics((160, 120))


def test_plane_depth_matches_analytic(small):
    # A plane slanted by ~50 deg covering the whole view: a 0.5 px convention error would show.
    R = meshes.rotation("y", 0.8) @ meshes.rotation("x", 0.35)
    v, f = meshes.plane(20.0, 20.0, 2.0)
    centre = np.array([0.1, -0.05, 1.2])
    verts = v @ R.T + centre
    depth, normal = MeshRenderer(small).render(verts, f)
    truth = plane_depth(small, R[:, 2], centre)
    assert (depth > 0).all()
    assert np.abs(depth - truth).max() < 5e-5
    assert np.abs(synth.depth_to_png(depth) / 1000.0 - truth).max() <= 0.0005 + 1e-6      # --noise none
    shifted = plane_depth(replace(small, cx=small.cx + 0.5), R[:, 2], centre)
    assert np.abs(shifted - truth).max() > 1e-3            # the test can tell a half-pixel shift
    facing = -np.sign(R[:, 2] @ centre) * R[:, 2]
    assert np.abs(normal - facing).max() < 1e-5


def test_sphere_depth_matches_analytic(small):
    centre, radius = np.array([0.05, -0.03, 0.9]), 0.15
    v, f = meshes.sphere(radius, 0.005)
    depth, normal = MeshRenderer(small).render(v + centre, f)
    d = rays(small)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = d @ centre
    disc = b * b - (centre @ centre - radius ** 2)
    t = b - np.sqrt(np.maximum(disc, 0))
    truth = np.where(disc > 0, t * d[..., 2], 0.0)
    hit = t[..., None] * d
    truth_normal = (hit - centre) / radius
    cos = np.abs(np.sum(truth_normal * d, -1))
    both = (depth > 0) & (truth > 0)
    iou = both.sum() / ((depth > 0) | (truth > 0)).sum()
    assert iou > 0.97
    inner = both & (cos > np.cos(np.deg2rad(75)))
    err = np.abs(depth - truth)[inner]
    assert err.max() < 5e-4 and np.median(err) < 1e-4
    assert np.abs(synth.depth_to_png(depth) / 1000.0 - truth)[inner].max() < 1e-3
    assert np.sum(normal * truth_normal, -1)[inner].min() > 0.995


def test_axial_noise_follows_model_on_a_plane():
    intr = synth.default_intrinsics((320, 240))
    ones = np.ones((240, 320), np.float32)
    ray_cos = 1.0 / np.linalg.norm(rays(intr), axis=-1)
    crop = (slice(10, -10), slice(10, -10))
    ratios = []
    for z in (0.6, 1.0, 1.6, 2.4):
        noisy = noise.kinect_noise(z * ones, ray_cos, intr, np.random.default_rng(1))
        stored = synth.depth_to_png(noisy)[crop] / 1000.0
        valid = stored > 0
        assert valid.mean() > 0.97
        ratios.append((stored[valid] - z).std() / noise.axial_sigma(z, 0.0))
        # Kinect's 1/8 px disparity steps (before the PNG's millimetres)
        steps = intr.fx * 2 * 0.075 / noisy[noisy > 0] * 8        # native 640 px focal length
        assert np.abs(steps - np.rint(steps)).max() < 1e-3
    assert np.allclose(ratios, 1.0, atol=0.12), ratios

    # A plane turned 70 deg: incidence runs from ~40 deg to grazing across the view, and the
    # spread follows the per-pixel model, with the angle term past 60 deg.
    R = meshes.rotation("y", np.deg2rad(70))
    depth = plane_depth(intr, R[:, 2], np.array([0.0, 0.0, 1.2]))
    depth = np.where((depth > 0) & (depth < 3), depth, 0).astype(np.float32)
    cos = np.abs(rays(intr) @ R[:, 2]) / np.linalg.norm(rays(intr), axis=-1)
    noisy = noise.kinect_noise(depth, cos, intr, np.random.default_rng(2))[crop]
    theta = np.degrees(np.arccos(cos))[crop]
    sigma = noise.axial_sigma(depth, np.arccos(cos))[crop]
    base = noise.axial_sigma(depth, 0.0)[crop]
    for lo, hi in ((40, 58), (62, 78)):
        band = (theta > lo) & (theta < hi) & (depth[crop] > 0)
        valid = band & (noisy > 0)
        assert valid.sum() > 0.9 * band.sum() and band.sum() > 2000
        assert abs(((noisy - depth[crop]) / sigma)[valid].std() - 1.0) < 0.12
    assert np.mean(sigma[valid] / base[valid]) > 1.25


def test_dropouts_shadow_and_grazing():
    intr = synth.default_intrinsics((320, 240))
    depth = np.full((240, 320), 1.2, np.float32)
    depth[80:160, 120:200] = 0.8                       # a square in front of a wall
    cos = np.ones_like(depth)
    shadow = noise.projector_shadow(depth, intr.fx)
    expected = intr.fx * 0.075 * (1 / 0.8 - 1 / 1.2)   # band width in pixels, left of the square
    widths = shadow[80:160].sum(1)
    assert np.all(np.abs(widths - expected) <= 1.0) and not shadow[:, 200:].any()
    assert shadow[80:160, 120 - int(expected):120].all()
    noisy = noise.kinect_noise(depth, cos, intr, np.random.default_rng(0))
    left = [(noisy[r, 100:120] == 0).sum() for r in range(90, 150)]
    right = [(noisy[r, 200:220] == 0).sum() for r in range(90, 150)]
    assert abs(np.median(left) - expected) <= 1.5 and np.median(right) <= 1

    # Grazing incidence: a plane turned ~60-88 deg across the view loses everything past 80 deg.
    R = meshes.rotation("y", np.deg2rad(74))
    depth = plane_depth(intr, R[:, 2], np.array([0.0, 0.0, 1.5])).astype(np.float32)
    depth[~(depth > 0) | (depth > 4.0)] = 0
    cos = np.abs(rays(intr) @ R[:, 2]) / np.linalg.norm(rays(intr), axis=-1)
    noisy = noise.kinect_noise(depth, cos, intr, np.random.default_rng(3))
    theta = np.degrees(np.arccos(cos))
    inner = (slice(5, -5), slice(5, -5))
    assert (theta[inner] > 80).sum() > 1000 and (theta[inner] < 78).sum() > 1000
    assert not noisy[inner][theta[inner] > 80.5].any()
    assert (noisy[inner][(theta[inner] < 78) & (depth[inner] > 0)] > 0).mean() > 0.95


def test_every_scene_renders_and_loads(tmp_path):
    for name in SCENES:
        out = synth.generate(name, tmp_path / name, frames=3, size=(96, 72), noise="kinect", seed=1)
        seq = open_sequence(out)
        assert len(seq) == 3 and seq.layout == "volumedeform"
        assert (seq.intrinsics.width, seq.intrinsics.height) == (96, 72) and seq.intrinsics.fx == 550 * 96 / 640
        for _, depth in seq.frames():
            assert (depth > 0).sum() > 50, name
        gt = synth.load_groundtruth(out)
        assert gt.vertices.shape == (3, len(gt.moving), 3) and gt.faces.max() < len(gt.moving)
        assert np.allclose(gt.camera_to_world[0], np.eye(4))
    again = synth.generate("touch", tmp_path / "again", frames=3, size=(96, 72), seed=1)
    other = synth.generate("touch", tmp_path / "other", frames=3, size=(96, 72), seed=2)
    read = [cv2.imread(str(p / "frame-000002.depth.png"), -1) for p in (tmp_path / "touch", again, other)]
    assert np.array_equal(read[0], read[1]) and not np.array_equal(read[0], read[2])


@pytest.mark.slow
def test_scene_motions_are_plausible_and_in_view():
    intr = synth.default_intrinsics((640, 480))
    for name, scene in SCENES.items():
        verts, cam, anim = synth.scene_frames(name, scene.default_frames)
        s = synth.motion_stats(verts, anim.faces, anim.moving, cam)
        assert s["max_strain"] < scene.max_strain, (name, s)
        assert s["max_edge_m"] < 0.0078, (name, s)        # 5 mm grids (diagonals 7 mm)
        if name in ("fast", "fast-wall"):        # the same ball
            assert 0.03 <= s["max_step_m"] <= 0.05, s
        else:
            assert s["max_step_m"] < 0.013, (name, s)
        travel = np.linalg.norm(np.diff(cam[:, :3, 3], axis=0), axis=1).sum()
        least = {"orbit": 0.5, "wall-slide": 0.25}.get(name)     # the scenes whose camera moves
        assert (travel > least) if least else (travel == 0), (name, travel)
        if name == "wall-slide":        # the wall fills every frame's view: its image corners' rays hit it
            corners = np.array([[(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0] for u in (0, 639) for v in (0, 479)])
            z = verts[0, 0, 2]
            for T in cam:
                d = corners @ T[:3, :3].T
                hit = T[:3, 3] + d * ((z - T[2, 3]) / d[:, 2:])
                assert (hit[:, 0] > verts[0, :, 0].min()).all() and (hit[:, 0] < verts[0, :, 0].max()).all()
                assert (hit[:, 1] > verts[0, :, 1].min()).all() and (hit[:, 1] < verts[0, :, 1].max()).all()
            continue
        pts = verts[:, anim.moving] if anim.moving.any() else verts
        uv = np.stack([intr.fx * pts[..., 0] / pts[..., 2] + intr.cx, intr.fy * pts[..., 1] / pts[..., 2] + intr.cy], -1)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < 640) & (uv[..., 1] >= 0) & (uv[..., 1] < 480) & (pts[..., 2] > 0.5)
        assert inside.mean(axis=1).min() > 0.95, name

    def gap(name, frame):
        v, _, anim = synth.scene_frames(name, frame + 1)
        a, b = v[frame][anim.part == 0], v[frame][anim.part == 1]
        return KDTree(a).query(b, k=1)[0].min()

    assert gap("touch", 0) > 0.02 and gap("touch", 30) < 0.001 and gap("touch", 60) > 0.02
    assert gap("release", 0) < 0.001 and gap("release", 30) > 0.02


def test_cli_functions(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    synth.add_arguments(parser)
    assert synth.run(parser.parse_args(["--list"])) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [l.split()[0] for l in lines] == list(SCENES) and len(lines) >= 5
    with pytest.raises(InputError):
        synth.run(parser.parse_args(["nosuch", "--out", str(tmp_path / "x")]))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    cv2.imwrite(str(foreign / "frame-000000.depth.png"), np.zeros((8, 8), np.uint16))
    with pytest.raises(InputError):
        synth.run(parser.parse_args(["twist", "--out", str(foreign), "--frames", "1", "--size", "32x24"]))
    args = parser.parse_args(["twist", "--out", str(tmp_path / "t"), "--frames", "2", "--size", "32x24",
                              "--noise", "none", "--no-progress"])
    assert synth.run(args) == 0 and len(list((tmp_path / "t").glob("frame-*.depth.png"))) == 2


def test_texture_moves_with_the_material(small):
    """A plane slid along itself by a whole number of pixels shows the same colours shifted:
    the texture is painted on the material, and the shading (same normal) does not change."""
    from surfelwarp.data_tools.texture import shade

    v, f = meshes.plane(4.0, 4.0, 0.5)
    verts = v + [0.0, 0.0, 1.0]
    renderer = MeshRenderer(small)
    slide = 10 / small.fx                              # 10 pixels at 1 m
    images = []
    for dx in (0.0, slide):
        depth, normal, material = renderer.render_maps(verts + [dx, 0.0, 0.0], f, verts)
        images.append(shade(depth, normal, material, None).astype(int))
    a, b = images
    assert np.abs(b[:, 10:] - a[:, :-10]).max() <= 2
    assert np.abs(b - a).mean() > 10                   # the texture does vary: the check can fail
    depth, _, _ = renderer.render_maps(verts + [5.0, 0.0, 0.0], f, verts)   # out of view
    blank = shade(depth, np.zeros(depth.shape + (3,)), np.zeros(depth.shape + (3,)), None)
    assert (blank == np.rint(255 * np.array(texture_background()))).all()


def test_plain_material_is_one_grey_under_the_light(tmp_path):
    """limb-plainwall and plainlimb-wall: limb-wall's frames with the wall's or the limb's
    texture left out; only the plain surface's colour differs (one albedo, shaded), the depth
    and ground truth are limb-wall's."""
    from surfelwarp.data_tools.texture import PLAIN_ALBEDO

    frames = {}
    for name in ("limb-wall", "limb-plainwall", "plainlimb-wall"):
        out = synth.generate(name, tmp_path / name, frames=1, size=(160, 120), noise="none")
        depth = cv2.imread(str(out / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
        rgb = cv2.imread(str(out / "frame-000000.color.png")).astype(float)
        frames[name] = depth, rgb.mean(-1), np.ptp(rgb, axis=-1)
    depth, _, _ = frames["limb-wall"]
    wall, limb = depth >= 1100, (depth > 0) & (depth < 1100)
    assert limb.sum() > 300 and wall.sum() > 10000
    for name, plain in (("limb-plainwall", wall), ("plainlimb-wall", limb)):
        d, grey, spread = frames[name]
        assert np.array_equal(d, depth)
        assert spread[plain].max() <= 1 and np.all(grey[plain] <= 255 * PLAIN_ALBEDO + 1)     # grey, shaded
        assert np.std(grey[~plain & (depth > 0)]) > 20                                        # the other textured


def texture_background():
    from surfelwarp.data_tools.texture import BACKGROUND_RGB
    return BACKGROUND_RGB


def test_synth_writes_registered_colour(tmp_path):
    out = synth.generate("roll", tmp_path / "roll", frames=2, size=(160, 120), noise="none")
    color = cv2.imread(str(out / "frame-000001.color.png"), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(out / "frame-000001.depth.png"), cv2.IMREAD_UNCHANGED)
    assert color.dtype == np.uint8 and color.shape == (120, 160, 3)
    # the ball and table are textured, the space behind them the plain background (BGR on disk)
    drawn = depth > 0
    assert color[drawn].std() > 20 and (color[~drawn] == [69, 64, 64]).all()


def test_room_light_stays_where_the_first_camera_left_it():
    """Known answer: under the room's lamp a world normal's Lambert term (n . l in the camera
    frame) is the same from every camera; the camera's lamp is the same direction in each."""
    from surfelwarp.data_tools.texture import LIGHT_DIRECTION, light_direction
    from surfelwarp.geometry.se3 import se3_exp

    rng = np.random.default_rng(2)
    poses = [se3_exp(np.concatenate([rng.normal(0.0, 0.5, 3), rng.normal(0.0, 0.2, 3)])) for _ in range(4)]
    n_world = rng.normal(size=(10, 3))
    n_world /= np.linalg.norm(n_world, axis=1, keepdims=True)
    lit = [(n_world @ T[:3, :3]) @ light_direction("room", T, poses[0]) for T in poses]   # n_c = R^T n_w
    np.testing.assert_allclose(lit[1:], np.repeat(lit[:1], 3, 0), atol=1e-12)
    np.testing.assert_allclose(lit[0], n_world @ poses[0][:3, :3] @ LIGHT_DIRECTION, atol=1e-12)
    assert np.abs(np.subtract(*[(n_world @ T[:3, :3]) @ LIGHT_DIRECTION for T in poses[:2]])).max() > 0.1
    assert all(light_direction("camera", T, poses[0]) is LIGHT_DIRECTION for T in poses)
    with pytest.raises(ValueError):
        light_direction("sun", poses[0], poses[0])


def test_synth_room_light(tmp_path):
    """The first frame is lit alike by both lamps; once the camera has moved round the still
    life, not; an unknown light is a clear error that writes nothing."""
    frames = {}
    for light in ("camera", "room"):
        out = synth.generate("orbit", tmp_path / light, frames=6, size=(160, 120), noise="none", light=light)
        frames[light] = [cv2.imread(str(out / f"frame-{i:06d}.color.png")).astype(int) for i in (0, 5)]
    assert np.array_equal(frames["camera"][0], frames["room"][0])
    assert str(np.load(tmp_path / "room" / "groundtruth.npz")["light"]) == "room"
    assert np.abs(frames["camera"][1] - frames["room"][1]).max() > 10
    with pytest.raises(InputError):
        synth.generate("orbit", tmp_path / "sun", frames=1, size=(32, 24), light="sun")
    assert not (tmp_path / "sun").exists()
    parser = argparse.ArgumentParser()
    synth.add_arguments(parser)
    assert parser.parse_args(["orbit", "--out", "x", "--light", "room"]).light == "room"
