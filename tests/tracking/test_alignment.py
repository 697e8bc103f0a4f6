"""How well the live model and the depth explain each other (alignment.py), and the
reinitialisation trigger that reads it."""
import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import se3_exp, transform_points
from surfelwarp.methods.surfelwarp.reinit import ReinitParams, ReinitTrigger
from surfelwarp.preprocess import preprocess
from surfelwarp.tracking.alignment import AlignmentParams, explained_pixels, measure, model_support

INTR = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)
T = se3_exp(np.array([0.05, -0.1, 0.02, 0.2, 0.1, -0.05]))     # camera off the world origin


@pytest.fixture(scope="module")
def plane():
    """A wall at 1 m filling the view, its depth surfels as a world-frame model."""
    obs = preprocess(np.full((INTR.height, INTR.width), 1.0, np.float32), INTR, 0, 0)
    s = obs.surfels()
    return obs, transform_points(T, s["position"].astype(np.float64)), s["normal"] @ T[:3, :3].T


def shifted(points, normals, v):
    """The model moved by v along the camera's axes (world frame)."""
    return points + T[:3, :3] @ np.asarray(v, np.float64), normals


def test_aligned_model_explains_the_depth_and_is_supported(plane):
    obs, p, n = plane
    a = measure(p, n, T, obs.depth_m, obs.vertex_map, obs.valid, INTR)
    assert a.unsupported_fraction < 0.001 and a.unexplained_fraction < 0.001
    assert a.valid_pixels == obs.num_valid and 0.8 * obs.num_valid < a.judged_points <= obs.num_valid


def test_a_model_off_the_surface_is_unsupported_and_explains_nothing(plane):
    obs, p, n = plane
    a = measure(*shifted(p, n, [0, 0, -0.03]), T, obs.depth_m, obs.vertex_map, obs.valid, INTR)
    assert a.unsupported_fraction > 0.99 and a.unexplained_fraction > 0.99
    # 3 cm behind the observed wall it is occluded, not contradicted: not judged.
    a = measure(*shifted(p, n, [0, 0, 0.03]), T, obs.depth_m, obs.vertex_map, obs.valid, INTR)
    assert a.judged_points == 0 and a.unexplained_fraction > 0.99


def test_a_model_slid_half_off_leaves_half_the_depth_unexplained(plane):
    obs, p, n = plane
    cols = np.flatnonzero(obs.valid.any(axis=0))
    width = (cols[-1] - cols[0] + 1) / INTR.fx     # metres of valid depth across the view at 1 m
    slid = shifted(p, n, [0.5 * width, 0, 0])
    a = measure(*slid, T, obs.depth_m, obs.vertex_map, obs.valid, INTR)
    assert a.unexplained_fraction == pytest.approx(0.5, abs=0.05)
    assert a.unsupported_fraction < 0.01           # what is still in view is on the wall


def test_windows_and_gates():
    """One point per pixel is enough for its 3x3 neighbours; 1 cm is the gate."""
    depth = np.full((INTR.height, INTR.width), 1.0, np.float32)
    obs = preprocess(depth, INTR, 0, 0)
    rows, cols = np.mgrid[20:100:3, 20:140:3]
    pts = obs.vertex_map[rows.ravel(), cols.ravel()]
    explained = explained_pixels(pts, obs.vertex_map, obs.valid, INTR)
    assert explained[20:98, 20:138].all() and not explained[5:15].any()
    off = pts - [0, 0, 0.012]                      # 12 mm in front of the wall
    assert not explained_pixels(off, obs.vertex_map, obs.valid, INTR).any()
    assert explained_pixels(off, obs.vertex_map, obs.valid, INTR, AlignmentParams(support_m=0.015)).any()
    judged, supported = model_support(off, np.tile([0.0, 0.0, -1.0], (len(off), 1)), obs.depth_m, obs.vertex_map,
                                      obs.valid, INTR)
    assert judged.all() and not supported.any()


def test_trigger_reads_both_fractions():
    """A slid model keeps a small RMS: the fractions trigger. Model points without depth do
    alone (fingers part, the surfels skinned to both stay between them, the depth explained);
    unexplained depth alone does not (a part coming into view is appended)."""
    from surfelwarp.tracking.alignment import Alignment
    slid = Alignment(unsupported_fraction=0.3, unexplained_fraction=0.08, judged_points=1000, valid_pixels=1000)
    good = Alignment(0.02, 0.01, 1000, 1000)
    only_unsupported = Alignment(0.3, 0.01, 1000, 1000)
    only_unexplained = Alignment(0.02, 0.08, 1000, 1000)

    def fired(alignment, frames=25):
        trigger, out = ReinitTrigger(ReinitParams()), []
        for i in range(frames):
            if trigger.update(0.0004, 0, 1000, alignment):
                out.append(i)
                trigger.reset()                    # as a reinitialisation does
        return out

    assert fired(good) == [] and fired(only_unexplained) == [] and fired(None) == []
    assert fired(slid) == [9, 19] and fired(only_unsupported) == [9, 19]    # min_interval_frames apart


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("window_px", [1, 2])
def test_compiled_window_searches_equal_the_numpy_references(dtype, window_px):
    """A bumpy wall with holes and model points scattered about the 1 cm gate (half of them
    within a float32 step of it): the compiled searches give the references' booleans exactly."""
    from surfelwarp.tracking.alignment import explained_pixels_reference, model_support_reference
    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:INTR.height, 0:INTR.width]
    depth = (1.0 + 0.05 * np.sin(cols / 7.0) * np.cos(rows / 5.0)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = 0
    depth[40:60, 30:70] = 0
    obs = preprocess(depth, INTR, 0, 0)
    pick = rng.choice(obs.num_valid, 3000)
    pts = obs.vertex_map[obs.valid][pick].astype(np.float64)
    offset = rng.normal(0, 0.008, (len(pts), 3))
    at_gate = rng.random(len(pts)) < 0.5
    offset[at_gate] *= 0.01 / np.linalg.norm(offset[at_gate], axis=1, keepdims=True)
    pts = (pts + offset + rng.normal(0, 0.002, (len(pts), 3)) * [1, 1, 0]).astype(dtype)
    normals = np.where(rng.random((len(pts), 1)) < 0.8, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]).astype(dtype)
    params = AlignmentParams(window_px=window_px)
    args = (obs.vertex_map, obs.valid, INTR, params)
    explained = explained_pixels(pts, *args)
    assert np.array_equal(explained, explained_pixels_reference(pts, *args))
    assert 0.05 < explained.sum() / obs.num_valid < 0.98
    args = (obs.depth_m, obs.vertex_map, obs.valid, INTR, params)
    judged, supported = model_support(pts, normals, *args)
    ref_judged, ref_supported = model_support_reference(pts, normals, *args)
    assert np.array_equal(judged, ref_judged) and np.array_equal(supported, ref_supported)
    assert 0.1 < supported.sum() / judged.sum() < 0.9
