"""Surfel colour: fused with the position's confidence weights, taken from the pixel on appending,
written to the PLYs only when the input has colour."""
import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.ply import COLOR_FIELDS, read_ply
from surfelwarp.io.sequence import open_sequence
from surfelwarp.methods.surfelwarp.appending import append_candidates
from surfelwarp.methods.surfelwarp.fusion import Correspondences, fuse
from surfelwarp.methods.surfelwarp.pipeline import SurfelWarpMethod
from surfelwarp.methods.surfelwarp.surfels import SurfelModel
from surfelwarp.preprocess import preprocess
from surfelwarp.run import run_sequence

from conftest import COLOR_FILES, SPHERE_RGB, WALL_RGB, two_colours, write_sequence

K = Intrinsics(100.0, 100.0, 39.5, 29.5, 80, 60)
PLAIN_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "ref_x", "ref_y", "ref_z", "radius", "confidence", "id")


def plane(color=None, frame=0):
    """A tilted plane about 1 m away in camera = world coordinates."""
    u, v = np.meshgrid((np.arange(K.width) - K.cx) / K.fx, (np.arange(K.height) - K.cy) / K.fy)
    n = np.array([0.2, -0.1, -1.0])
    depth = (n @ [0.0, 0.0, 1.0]) / (n[0] * u + n[1] * v + n[2])
    return preprocess(depth.astype(np.float32), K, frame, frame, color=color)


def random_colour(seed):
    return np.random.default_rng(seed).integers(0, 256, (K.height, K.width, 3), dtype=np.uint8)


def surfels_of(obs, color=None, confidence_scale=1.0) -> SurfelModel:
    """One surfel on each valid pixel (row-major), so surfel i is pixel i of np.nonzero(valid)."""
    s = obs.surfels()
    return SurfelModel.from_points(s["position"], s["normal"], s["radius"], confidence_scale * s["confidence"], 0, 0,
                                   color=color)


def test_fusion_weights_colour_as_the_position():
    first = plane(random_colour(1))
    model = surfels_of(first, first.surfels()["color"], confidence_scale=3.0)
    assert np.array_equal(model.color_weight, model.confidence)
    second = plane(random_colour(2), frame=1)
    rows, cols = np.nonzero(second.valid)
    k = np.arange(0, len(rows), 3)                 # every third surfel fuses its own pixel
    fused, _ = fuse(model, np.eye(4), second, Correspondences(rows[k], cols[k], k), 1)
    c_old, c_depth = model.confidence[k], second.confidence_map[rows[k], cols[k]]
    expect = (c_old[:, None] * model.color[k] + c_depth[:, None] * second.color[rows[k], cols[k]]) \
        / (c_old + c_depth)[:, None]
    assert np.allclose(fused.color[k], expect, atol=1e-3)
    assert np.abs(fused.color[k] - model.color[k]).mean() > 10      # the colours really moved
    assert np.array_equal(fused.color_weight, fused.confidence)
    untouched = np.setdiff1d(np.arange(len(model)), k)
    assert np.array_equal(fused.color[untouched], model.color[untouched])
    # A frame without colour moves no colour and adds no colour weight.
    again, _ = fuse(fused, np.eye(4), plane(None, frame=2), Correspondences(rows[k], cols[k], k), 2)
    assert np.array_equal(again.color, fused.color) and np.array_equal(again.color_weight, fused.color_weight)
    assert np.all(again.confidence[k] > fused.confidence[k])


def test_surfels_never_seen_in_colour_take_the_first_colour_whole():
    model = surfels_of(plane(None))
    assert np.all(model.color == 0) and np.all(model.color_weight == 0)
    obs = plane(random_colour(3), frame=1)
    rows, cols = np.nonzero(obs.valid)
    k = np.arange(len(rows))
    fused, _ = fuse(model, np.eye(4), obs, Correspondences(rows, cols, k), 1)
    assert np.array_equal(fused.color, obs.color[rows, cols].astype(np.float32))
    assert np.array_equal(fused.color_weight, obs.confidence_map[rows, cols])


def test_appended_surfels_take_their_pixel_colour():
    obs = plane(random_colour(4))
    field = WarpField.from_points(obs.vertex_map[obs.valid])
    every = np.ones(obs.valid.shape, bool)
    res = append_candidates(obs, every, np.eye(4), field, 4)
    assert len(res) == obs.num_valid
    assert np.array_equal(res.color, obs.color[res.pixel_rows, res.pixel_cols].astype(np.float32))
    s = res.surfels(time=0, first_id=0)
    assert np.array_equal(s.color, res.color) and np.array_equal(s.color_weight, s.confidence)
    plain = append_candidates(plane(None), every, np.eye(4), field, 4).surfels(time=0, first_id=0)
    assert plain.color.shape == (len(plain), 3) and not plain.color.any() and not plain.color_weight.any()


def test_select_and_concatenate_carry_colour():
    obs = plane(random_colour(5))
    model = surfels_of(obs, obs.surfels()["color"])
    picked = model.select(np.array([5, 2]))
    assert np.array_equal(picked.color, model.color[[5, 2]]) and np.array_equal(picked.color_weight,
                                                                                 model.color_weight[[5, 2]])
    both = picked.concatenate(model.select(np.array([7])))
    assert np.array_equal(both.color, model.color[[5, 2, 7]])


def class_colours(table):
    """RGB of the sphere's vertices and of the wall's (the sphere reaches 1.0 m, the wall is at 1.5 m)."""
    rgb = np.stack([table[c] for c in COLOR_FIELDS], 1).astype(int)
    return rgb[table["z"] < 1.4], rgb[table["z"] > 1.45]


def assert_painted(path):
    table, _ = read_ply(path)
    assert table.dtype.names == PLAIN_FIELDS + COLOR_FIELDS
    assert all(table.dtype[c] == np.dtype("u1") for c in COLOR_FIELDS)
    sphere, wall = class_colours(table)
    assert len(sphere) > 300 and len(wall) > 300
    assert np.abs(sphere - SPHERE_RGB).max() <= 2 and np.abs(wall - WALL_RGB).max() <= 2


@pytest.fixture(scope="module")
def painted(tmp_path_factory):
    root = tmp_path_factory.mktemp("painted")
    seq = write_sequence(root / "seq", frames=range(4), color=two_colours)
    method = SurfelWarpMethod(open_sequence(seq).intrinsics)
    run_sequence(open_sequence(seq), root / "out", method, save_every=2, progress=False)
    return root / "out", method


def test_run_writes_the_fused_colour(painted):
    out, method = painted
    for name in ("live/frame-000000.ply", "live/frame-000002.ply", "live/frame-000003.ply", "model.ply"):
        assert_painted(out / name)
    assert method.has_color and np.array_equal(method.model.color_weight, method.model.confidence)


def test_a_frame_without_colour_does_not_stop_the_run(tmp_path, capsys):
    seq = write_sequence(tmp_path / "seq", frames=range(4), color=two_colours)
    (seq / COLOR_FILES["volumedeform"].format(1)).unlink()
    run_sequence(open_sequence(seq), tmp_path / "out", SurfelWarpMethod(open_sequence(seq).intrinsics),
                 progress=False)
    assert capsys.readouterr().err.count("1 of 4 frames have no colour frame") == 1
    # Surfels first seen in frame 1 took their colour from the next frame that saw them.
    table, _ = read_ply(tmp_path / "out" / "model.ply")
    sphere, wall = class_colours(table)
    assert np.mean(np.all(np.abs(sphere - SPHERE_RGB) <= 2, 1)) > 0.99
    assert np.mean(np.all(np.abs(wall - WALL_RGB) <= 2, 1)) > 0.99


def test_run_without_colour_writes_no_colour_properties(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    method = SurfelWarpMethod(open_sequence(seq).intrinsics)
    run_sequence(open_sequence(seq), tmp_path / "out", method, progress=False)
    for name in ("live/frame-000001.ply", "model.ply"):
        assert read_ply(tmp_path / "out" / name)[0].dtype.names == PLAIN_FIELDS
    assert method.has_color is False and not method.model.color.any()
