"""Model reinitialisation (SurfelWarp Sec. VI-F): the trigger and the cleaning of S_live."""
from dataclasses import replace

import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import se3_exp, transform_points
from surfelwarp.methods.surfelwarp.reinit import ReinitParams, ReinitTrigger, unsupported_mask
from surfelwarp.preprocess import preprocess

K = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
VALID = 10_000


def run_trigger(trigger, frames):
    """Frames as (rmse_m, appended); the frame numbers (from 1) at which it fired."""
    return [i for i, (rmse, appended) in enumerate(frames, 1) if trigger.update(rmse, appended, VALID)]


def test_steady_noisy_tracking_never_triggers():
    # 7-Scenes-like: 2.4 mm RMS and 11 % appended on every frame is the sensor, not a failure.
    frames = [(0.0024 + 1e-4 * np.sin(i), 1100) for i in range(60)]
    assert run_trigger(ReinitTrigger(ReinitParams()), frames) == []


def test_misalignment_with_many_appended_triggers_after_consecutive_frames():
    good = [(0.0004, 100)] * 12
    bad = [(0.0015, 800)] * 5
    fired = run_trigger(ReinitTrigger(ReinitParams()), good + bad)
    assert fired[0] == 12 + 3          # the third consecutive struggling frame


def test_a_struggle_lasts_while_misaligned_though_the_depth_is_explained_again():
    # Appending explains last frame's depth, so "many appended" flickers during a struggle; the
    # misalignment is what lasts. Without it the struggle ends.
    good = [(0.0004, 100)] * 12
    assert run_trigger(ReinitTrigger(ReinitParams()), good + [(0.0015, 800), (0.0015, 100), (0.0015, 800)]) == [15]
    assert run_trigger(ReinitTrigger(ReinitParams()), good + [(0.0015, 800), (0.0004, 100), (0.0015, 800)]) == []


def test_a_long_struggle_does_not_raise_the_bar():
    trigger = ReinitTrigger(ReinitParams())
    fired = []
    for i, (rmse, appended) in enumerate([(0.0004, 100)] * 12 + [(0.0015, 800)] * 30, 1):
        if trigger.update(rmse, appended, VALID):
            fired.append(i)
            trigger.reset()
    assert fired == [15, 25, 35]


@pytest.mark.parametrize("bad", [(0.0015, 100),       # high energy, few appended: not enough
                                 (0.0004, 3000),      # many appended (new geometry), energy normal
                                 (0.0009, 800)])      # above 2x the median, but under the 1 mm floor
def test_either_sign_alone_does_not_trigger(bad):
    assert run_trigger(ReinitTrigger(ReinitParams()), [(0.0004, 100)] * 12 + [bad] * 10) == []


def test_interval_reset_and_periodic():
    trigger = ReinitTrigger(ReinitParams())
    # Struggling from the start: not before min_interval_frames, and again only that long after a reset.
    fired = []
    for i in range(1, 40):
        if trigger.update(float("nan"), 5000, VALID):
            fired.append(i)
            trigger.reset()
    assert fired == [10, 20, 30]
    periodic = ReinitTrigger(ReinitParams(every_frames=7, consecutive_frames=1000))
    assert run_trigger(periodic, [(0.0004, 0)] * 15)[:1] == [7]
    assert run_trigger(ReinitTrigger(ReinitParams(enabled=False, every_frames=2)), [(1.0, 9000)] * 30) == []


@pytest.fixture(scope="module")
def plane_obs():
    """A fronto-parallel wall 1.2 m away, seen whole."""
    return preprocess(np.full((K.height, K.width), 1.2, np.float32), K, frame_index=0, time=0)


def pixel_points(uv, z):
    uv = np.asarray(uv, float)
    return np.stack([(uv[:, 0] - K.cx) * z / K.fx, (uv[:, 1] - K.cy) * z / K.fy, np.full(len(uv), z)], 1)


def test_unsupported_surfels_are_the_visible_ones_without_depth(plane_obs):
    T_cam = se3_exp(np.array([0.1, -0.2, 0.05, 0.3, -0.1, 0.2]))      # camera -> world
    uv = np.array([[40, 30], [80, 60], [120, 90], [60, 70]])
    on_wall = pixel_points(uv, 1.2)
    in_front = pixel_points(uv, 0.9)          # the wall is seen behind them: contradicted
    behind = pixel_points(uv, 1.5)            # hidden by the wall: occluded, not contradicted
    near_wall = pixel_points(uv, 1.2 - 0.006)  # within support_distance_m
    outside = pixel_points(np.array([[5, 60], [80, 3]]), 1.2)   # in the cropped border
    points = np.concatenate([on_wall, in_front, behind, near_wall, outside])
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    normals[1] = [0.0, 0.0, 1.0]              # faces away: not expected to be seen
    normals[5] = [0.0, 0.0, 1.0]
    world = transform_points(T_cam, points)
    drop = unsupported_mask(world.astype(np.float32), (normals @ T_cam[:3, :3].T).astype(np.float32),
                            T_cam, plane_obs)
    expected = np.zeros(len(points), bool)
    expected[4:8] = True                      # in front of the wall ...
    expected[5] = False                       # ... except the one facing away
    assert drop.tolist() == expected.tolist()
    # A wider support distance accepts the ones 30 cm in front.
    loose = unsupported_mask(world.astype(np.float32), (normals @ T_cam[:3, :3].T).astype(np.float32),
                             T_cam, plane_obs, replace(ReinitParams(), support_distance_m=0.35))
    assert not loose.any()
