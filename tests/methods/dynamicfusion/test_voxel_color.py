"""Voxel colour: a running average with the tsdf's weights within the truncation band, sampled at
the mesh vertices, written to the PLYs only when the input has colour."""
import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.ply import COLOR_FIELDS, VERTEX_FIELDS, read_ply
from surfelwarp.io.sequence import open_sequence
from surfelwarp.methods.dynamicfusion.params import DynamicFusionParams
from surfelwarp.methods.dynamicfusion.pipeline import DynamicFusionMethod
from surfelwarp.methods.dynamicfusion.tsdf import TSDFParams, TSDFVolume, fuse, sample_color
from surfelwarp.run import run_sequence

from conftest import SPHERE_RGB, WALL_RGB, two_colours, write_sequence

K = Intrinsics(40.0, 40.0, 19.5, 14.5, 40, 30)
P = TSDFParams(voxel_size_m=0.01, truncation_m=0.03)
# 2 cm voxels: the 64x48 test sequences' pixels are 2.5 cm wide on their wall.
COARSE = DynamicFusionParams(tsdf=TSDFParams(voxel_size_m=0.02, truncation_m=0.06))


def plane_volume():
    """A fronto-parallel plane at z = 0.5 m seen by an identity camera, and a volume around it."""
    return np.full((K.height, K.width), 0.5, np.float32), TSDFVolume.empty((-0.15, -0.1, 0.3), (31, 21, 41), 0.01,
                                                                           color=True)


def voxel_pixels(volume):
    """(V,) flat pixel each voxel centre projects to (the identity camera)."""
    c = volume.voxel_centres().astype(np.float64)
    u = np.rint(K.fx * c[:, 0] / c[:, 2] + K.cx).astype(int)
    v = np.rint(K.fy * c[:, 1] / c[:, 2] + K.cy).astype(int)
    return v * K.width + u


def test_colour_is_the_tsdf_weighted_average_within_the_band():
    depth, volume = plane_volume()
    halves = np.zeros((K.height, K.width, 3), np.uint8)
    halves[:, :20], halves[:, 20:] = (250, 10, 10), (10, 10, 250)
    fuse(volume, None, 1.0, np.eye(4), depth, K, P, color=halves)
    fuse(volume, None, 3.0, np.eye(4), depth, K, P, color=np.full_like(halves, 90))
    tsdf, weight = volume.tsdf.reshape(-1), volume.weight.reshape(-1)
    color, color_weight = volume.color.reshape(-1, 3), volume.color_weight.reshape(-1)
    band = (weight > 0) & (tsdf < 1)
    free = (weight > 0) & (tsdf == 1)        # farther than tau in front of the plane
    assert band.sum() > 1000 and free.sum() > 1000
    expect = (1 * halves.reshape(-1, 3)[voxel_pixels(volume)[band]] + 3 * 90.0) / 4
    assert np.abs(color[band] - expect).max() < 1e-3
    assert np.array_equal(color_weight[band], weight[band])
    assert not color_weight[free].any() and not color[free].any()
    # A frame without colour adds tsdf weight, not colour.
    before = color.copy()
    fuse(volume, None, 2.0, np.eye(4), depth, K, P)
    assert np.array_equal(volume.color.reshape(-1, 3), before) and np.all(weight[band] == color_weight[band] + 2)
    assert volume.nbytes == volume.tsdf.nbytes * 6     # tsdf, weight, 3 colours, colour weight


def test_a_volume_without_colour_ignores_it():
    depth, _ = plane_volume()
    volume = TSDFVolume.empty((-0.15, -0.1, 0.3), (31, 21, 41), 0.01)
    fuse(volume, None, 1.0, np.eye(4), depth, K, P, color=np.zeros((K.height, K.width, 3), np.uint8))
    assert volume.color is None and volume.color_weight is None and volume.nbytes == volume.tsdf.nbytes * 2


def test_sample_color_is_trilinear_over_the_voxels_seen_in_colour():
    volume = TSDFVolume.empty((1.0, 2.0, 3.0), (4, 4, 4), 0.5, color=True)
    i, j, k = np.meshgrid(*(np.arange(4.0),) * 3, indexing="ij")
    volume.color[:] = np.stack([10 * i, 20 * j, 30 * k], -1)
    volume.color_weight[:] = 1
    point = volume.origin + np.array([1.25, 2.5, 0.75]) * 0.5
    assert np.allclose(sample_color(volume, point[None]), [[12.5, 50, 22.5]], atol=1e-4)
    volume.color_weight[2] = 0                     # the slab x = 2 was never seen in colour
    assert np.allclose(sample_color(volume, point[None]), [[10, 50, 22.5]], atol=1e-4)
    volume.color_weight[:] = 0
    assert np.array_equal(sample_color(volume, point[None]), [[0, 0, 0]])


def run_df(seq_dir, out):
    seq = open_sequence(seq_dir)
    method = DynamicFusionMethod(seq.intrinsics, COARSE)
    run_sequence(seq, out, method, save_every=2, progress=False)
    return method


def test_run_writes_the_fused_colour_on_the_mesh(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(4), color=two_colours)
    method = run_df(seq, tmp_path / "out")
    assert method.has_color
    for name in ("live/frame-000000.ply", "live/frame-000002.ply", "live/frame-000003.ply", "model.ply"):
        table, faces = read_ply(tmp_path / "out" / name)
        assert table.dtype.names == VERTEX_FIELDS + COLOR_FIELDS and faces is not None
        assert all(table.dtype[c] == np.dtype("u1") for c in COLOR_FIELDS)
        rgb = np.stack([table[c] for c in COLOR_FIELDS], 1).astype(int)
        sphere, wall = rgb[table["z"] < 1.35], rgb[table["z"] > 1.45]
        assert len(sphere) > 300 and len(wall) > 300
        assert np.abs(sphere - SPHERE_RGB).max() <= 2 and np.abs(wall - WALL_RGB).max() <= 2


def test_run_without_colour_writes_no_colour_properties(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    method = run_df(seq, tmp_path / "out")
    assert method.has_color is False and method.volume.color is None and method.mesh.colors is None
    for name in ("live/frame-000001.ply", "model.ply"):
        assert read_ply(tmp_path / "out" / name)[0].dtype.names == VERTEX_FIELDS


@pytest.mark.parametrize("colour_first", [True, False])
def test_empty_model_keeps_the_ply_layout(colour_first):
    """Before the model starts (too little depth), the PLYs still say whether there is colour."""
    from surfelwarp.preprocess import preprocess
    method = DynamicFusionMethod(K, COARSE)
    colour = np.zeros((K.height, K.width, 3), np.uint8) if colour_first else None
    method.process(preprocess(np.zeros((K.height, K.width), np.float32), K, 0, 0, color=colour))
    table, faces = method.live_vertices()
    assert len(table) == 0 and faces.shape == (0, 3)
    assert table.dtype.names == VERTEX_FIELDS + (COLOR_FIELDS if colour_first else ())
