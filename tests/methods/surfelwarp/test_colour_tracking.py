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


def test_colour_found_ahead_is_what_the_frame_finds(gl, monkeypatch):
    """`ahead` on a worker while the frame before is processed (as run.py calls it: colour work
    and free space) leaves the model the same to the bit as doing everything in the frame, also
    where what it found is stale: a new keyframe after it ran (frame 3) and a frame left out
    before the next (frame 4)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from surfelwarp.tracking import colour, tracker

    intr, obs = sliding_plane(6)
    calls, spaces = [], []
    real, real_space = colour.match_frames, tracker.FreeSpace
    in_frame = lambda: threading.current_thread() is threading.main_thread()    # noqa: E731
    monkeypatch.setattr(colour, "match_frames",     # counted when a frame matches, not `ahead`
                        lambda *a: calls.append(in_frame()) or real(*a))
    monkeypatch.setattr(tracker, "FreeSpace", lambda *a: spaces.append(in_frame()) or real_space(*a))

    def run(early: bool):
        params = SurfelWarpParams()
        tracking = replace(params.tracking, camera="static",
                           nonrigid=replace(params.tracking.nonrigid, feature_weight=100.0))
        method = SurfelWarpMethod(intr, replace(params, tracking=tracking))
        calls.clear()
        spaces.clear()
        with ThreadPoolExecutor(1) as worker:
            def ahead(*frames):
                if early:
                    for i in frames:
                        worker.submit(method.ahead, obs[i]).result()

            ahead(0)
            records = [method.process(obs[0])]
            ahead(1)
            records.append(method.process(obs[1]))
            ahead(2)
            coming = worker.submit(method.ahead, obs[3]) if early else None
            records.append(method.process(obs[2]))     # frame 3's features found meanwhile
            if coming is not None:
                coming.result()
            # A new keyframe, frame 1's features (not the last frame's, whose matches would be the
            # same): frame 3's pairs with the old one go.
            method.tracker.new_reference(obs[1], method.model.ids, method.model.ref_position)
            records.append(method.process(obs[3]))
            ahead(4, 5)                        # frame 4 left out: frame 5's matches with it go
            if early:                          # kept: the last two only (not every frame left out)
                ahead(4, 4, 5)
                assert [o.frame_index for o in method.tracker.colour._found.observations()] == [4, 5]
            records.append(method.process(obs[5]))
        return method.model, [(r.details[0].feature_matches, r.energy) for r in records[1:]], (sum(calls), sum(spaces))

    model, records, found_in_frames = run(early=False)
    model_ahead, records_ahead, found_in_frames_ahead = run(early=True)
    assert min(count for count, _ in records) > 100
    assert records_ahead == records                    # matches and energies of frames 1, 2, 3, 5
    for name in ("live_position", "live_normal", "ref_position", "ids"):
        assert getattr(model_ahead, name).tobytes() == getattr(model, name).tobytes(), name
    # every processed frame after the first matched its last one and built its free space in
    # the frame (4), and with `ahead` only frame 5 matched (its last observation, frame 3, was
    # not the one `ahead` saw) and none built its free space.
    assert (found_in_frames, found_in_frames_ahead) == ((4, 4), (1, 0))
