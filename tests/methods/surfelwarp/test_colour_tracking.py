"""End to end: a textured plane slides along itself, which depth cannot see. Depth alone
leaves the model where it was; with colour (features and flow from the model's texture) the
model follows the slide."""
from dataclasses import replace

import numpy as np
import pytest

from surfelwarp.data_tools import meshes
from surfelwarp.data_tools.render import MeshRenderer
from surfelwarp.data_tools.synth import default_intrinsics
from surfelwarp.data_tools.texture import shade
from surfelwarp.methods.surfelwarp import pipeline
from surfelwarp.methods.surfelwarp.pipeline import SurfelWarpMethod, SurfelWarpParams
from surfelwarp.preprocess import preprocess

STEP = np.array([0.006, -0.003, 0.0])      # a frame's slide, along the plane


def sliding_plane(frames: int):
    intr = default_intrinsics((320, 240))
    v, f = meshes.plane(3.0, 3.0, 0.1)       # wider than the view: no edge gives the slide away
    rest = v + [0.0, 0.0, 1.0]
    renderer = MeshRenderer(intr)
    out = []
    for i in range(frames):
        depth, normal, material = renderer.render_maps(rest + i * STEP, f, rest)
        out.append(preprocess(depth, intr, i, i, color=shade(depth, normal, material, None)))
    renderer.release()
    return intr, out


def track(intr, observations, feature_weight: float):
    params = SurfelWarpParams()
    tracking = replace(params.tracking, camera="static",
                       nonrigid=replace(params.tracking.nonrigid, feature_weight=feature_weight))
    method = SurfelWarpMethod(intr, replace(params, tracking=tracking))
    for obs in observations:
        record = method.process(obs)
    m = method.model
    first = m.t_init == 0                    # the first frame's surfels: their motion is known
    return m.live_position[first] - m.ref_position[first], record


@pytest.mark.parametrize("feature_weight", [0.0, 100.0])
def test_colour_sees_a_slide_depth_cannot(gl, feature_weight, monkeypatch):
    intr, observations = sliding_plane(4)
    drawn = []
    real = pipeline.colour_map
    monkeypatch.setattr(pipeline, "colour_map", lambda *a, **k: drawn.append(1) or real(*a, **k))
    moved, record = track(intr, observations, feature_weight)
    # the model's colour is drawn for the features only (3 frames after the first), not without them
    assert len(drawn) == (3 if feature_weight > 0 else 0)
    expected = 3 * STEP
    if feature_weight == 0:
        assert np.abs(moved).max() < 1e-3                     # depth alone: still
        assert record.details[0].feature_matches is None
    else:
        err = np.linalg.norm(np.median(moved, axis=0) - expected)
        assert err < 0.5 * 1.0 / intr.fx, (np.median(moved, axis=0), expected)    # half a pixel at 1 m
        assert record.details[0].feature_matches > 100
