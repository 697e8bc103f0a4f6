"""Colour pairs put on the model (tracking/colour.py): the last frame's points taken back to the
reference by the field that frame ended with, also when the nodes were carried on since."""
import numpy as np
import pytest

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, skin, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.tracking.colour import ColourMatcher
from surfelwarp.tracking.features import FeatureMatches, ModelView

INTR = Intrinsics(500.0, 500.0, 79.5, 59.5, 160, 120)


def plane_model(step_m: float):
    """Surfels one a pixel on a plane 1 m away (reference = where the last frame ended, the
    identity field), the field with every node carried on by step_m along x, and the model map
    drawn from the carried surfels: (ended, carried, ModelView, reference points)."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    ref = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    ended = WarpField.from_points(ref, WarpFieldParams(node_radius_m=0.025))
    transforms = ended.transforms.copy()
    transforms[:, 0, 3] += step_m
    carried = ended.with_transforms(transforms)
    knn, weights = skin(ref, ended.nodes, ended.params.k_skin, ended.sigma_m)
    live, _ = warp(ref, None, knn, weights, carried)
    index_map = np.full((INTR.height, INTR.width), -1, np.int64)
    px = np.rint(INTR.project(live)).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < INTR.width) & (px[:, 1] >= 0) & (px[:, 1] < INTR.height)
    index_map[px[inside, 1], px[inside, 0]] = np.flatnonzero(inside)
    view = ModelView(index_map, np.arange(len(ref)), live, np.arange(len(ref)), knn, weights, ref_position=ref)
    return ended, carried, view, ref


def last_frame_pairs(ref: np.ndarray, rows: np.ndarray) -> FeatureMatches:
    """Pairs of the last frame's points (where it saw the surface: the reference, camera =
    world) with points 1 cm farther along x in this frame."""
    pixels = INTR.project(ref[rows]).astype(np.float32)
    return FeatureMatches(pixels, pixels + 5.0, ref[rows], ref[rows] + [0.01, 0.0, 0.0])


@pytest.mark.parametrize("step_m", [0.004, 0.04])
def test_last_frame_pairs_go_back_by_the_field_that_frame_ended_with(step_m):
    """The nodes carried on by a step along the plane (which depth does not see): a last-frame
    point is taken back by the field the last frame ended with, to its own reference point;
    by the carried field (as before) it went back a step short, and its pair pulled the nodes
    on by twice their motion. A step beyond the features' reach of the drawn surfel (1 cm)
    leaves the pairs off the model; a shorter one keeps them."""
    ended, carried, view, ref = plane_model(step_m)
    rows = np.flatnonzero((np.abs(ref[:, 0]) < 0.04) & (np.abs(ref[:, 1]) < 0.04))
    matcher = ColourMatcher(INTR)
    pairs = last_frame_pairs(ref, rows)

    def gap(points, to):
        return np.linalg.norm(points[:, None] - to[None], axis=2).min(axis=1)

    fixed = matcher._on_model(pairs, view, carried, 1.0, ended)
    old = matcher._on_model(pairs, view, carried, 1.0)
    assert len(old) > 0.9 * len(rows) and gap(old.ref_points, ref[rows] - [step_m, 0, 0]).max() < 1e-6
    if step_m < 0.01:
        assert len(fixed) > 0.9 * len(rows) and gap(fixed.ref_points, ref[rows]).max() < 1e-9
    else:
        assert len(fixed) == 0
    # not carried (the field is the one the last frame ended with): the same pairs to the bit
    same = matcher._on_model(pairs, view, ended, 1.0, ended)
    plain = matcher._on_model(pairs, view, ended, 1.0)
    assert len(plain) > 0.9 * len(rows)
    assert same.ref_points.tobytes() == plain.ref_points.tobytes() and np.array_equal(same.index, plain.index)
