"""The full SurfelWarp pipeline (fusion, appending, removal, reinitialisation) end to end on
synthetic scenes, scored with `surfelwarp eval`; and its parameter file (--config)."""
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from surfelwarp.cli import main
from surfelwarp.config import load_params
from surfelwarp.data_tools import evaluate, synth
from surfelwarp.errors import InputError
from surfelwarp.io.ply import read_ply
from surfelwarp.methods.surfelwarp.params import SurfelWarpParams


def run(seq, out, *flags):
    assert main(["run", str(seq), "--out", str(out), "--no-progress", *map(str, flags)]) == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    root = tmp_path_factory.mktemp("sheet")
    seq = synth.generate("sheet", root / "seq", frames=16, size=(640, 480))
    out = root / "run"
    metrics = run(seq, out, "--save-every", 5)
    return seq, out, metrics, evaluate.evaluate(out, seq)


@pytest.mark.slow
def test_sheet_is_reconstructed_and_tracked(sheet):
    seq, out, metrics, res = sheet
    avg = res["average"]
    assert metrics["method"] == "surfelwarp" and metrics["config"]["method"]["fusion_enabled"] is True
    assert avg["accuracy_median_mm"] < 1.0
    assert avg["completeness_10mm_pct"] > 97 and avg["precision_5mm_pct"] > 97
    assert avg["epe_mean_mm"] < 8.0        # issue 5's figure; 6.3 measured (under 6 with the anchors off)
    frames = metrics["frames"]
    assert not any(f["reinitialized"] for f in frames)
    assert all(f["fused"] > 0.85 * f["surfels"] for f in frames[1:])   # most surfels see depth each frame
    assert {"motion", "fusion_maps", "fuse", "append", "remove", "inverse_warp", "extend"} <= frames[-1]["seconds"].keys()


@pytest.mark.slow
def test_model_stays_compact(sheet):
    seq, out, metrics, _ = sheet
    last = metrics["frames"][-1]
    valid = (cv2.imread(str(seq / f"frame-{last['frame']:06d}.depth.png"), cv2.IMREAD_UNCHANGED) > 0).sum()
    # Fused rather than piled up: about one surfel per observed pixel, not one per pixel per frame.
    assert last["surfels"] < 1.3 * valid
    counts = [f["surfels"] for f in metrics["frames"]]
    assert max(counts) < 1.2 * counts[0]
    plot = cv2.imread(str(out / "surfels.png"))
    assert plot is not None and plot.shape[1] >= 600


@pytest.mark.slow
def test_ids_persist_and_reference_positions_hold_still(sheet):
    _, out, _, _ = sheet
    early, _ = read_ply(out / "live" / "frame-000005.ply")
    late, _ = read_ply(out / "live" / "frame-000015.ply")
    assert len(np.unique(late["id"])) == len(late)
    common, i, j = np.intersect1d(early["id"], late["id"], return_indices=True)
    assert len(common) > 0.8 * len(early)
    # A surfel's reference position only moves by fusing new depth into it: within the noise.
    ref = lambda t, k: np.stack([t["ref_x"][k], t["ref_y"][k], t["ref_z"][k]], 1)  # noqa: E731
    drift = np.linalg.norm(ref(early, i) - ref(late, j), axis=1)
    assert np.median(drift) < 0.001 and np.percentile(drift, 95) < 0.004
    model, _ = read_ply(out / "model.ply")
    np.testing.assert_array_equal(np.sort(model["id"]), np.sort(late["id"]))


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("release")
    return synth.generate("release", root / "seq", frames=18, size=(320, 240)), root


@pytest.mark.slow
def test_release_reinitialises_and_drops_what_depth_contradicts(release, tmp_path):
    """Fingers touching at frame 0 open: the node graph ties them, tracking struggles, and
    Sec. VI-F rebuilds the reference from the cleaned live model."""
    seq, _ = release
    metrics = run(seq, tmp_path / "on", "--save-every", 1)
    fired = [f["frame"] for f in metrics["frames"] if f["reinitialized"]]
    assert len(fired) == 1 and 10 <= fired[0] <= 16
    after = [f for f in metrics["frames"] if f["frame"] >= fired[0]]
    assert all(f["reference_frame"] == fired[0] for f in after)
    assert next(f for f in after if f["frame"] == fired[0])["reinit_dropped"] > 0
    (tmp_path / "off.json").write_text('{"reinit": {"enabled": false}}')
    run(seq, tmp_path / "off", "--save-every", 1, "--config", tmp_path / "off.json")
    with_reinit = evaluate.evaluate(tmp_path / "on", seq)["frames"]
    without = evaluate.evaluate(tmp_path / "off", seq)["frames"]
    after_fire = [r["frame"] for r in with_reinit if r["frame"] > fired[0]]
    precision = lambda rows: np.mean([r["precision_5mm_pct"] for r in rows if r["frame"] in after_fire])  # noqa: E731
    assert precision(with_reinit) > precision(without) + 10


def test_config_file_overrides_and_is_recorded(release, tmp_path):
    seq, _ = release
    cfg = tmp_path / "params.toml"
    cfg.write_text("recent_draw = 'with'\n[fusion]\ndistance_threshold_m = 0.005\n[tracking.nonrigid]\nlambda_reg = 8\n"
                   "[tracking.hierarchy]\nenabled = true\n")
    params = load_params(cfg, SurfelWarpParams())
    assert params.fusion.distance_threshold_m == 0.005 and params.tracking.nonrigid.lambda_reg == 8.0
    assert params.fusion.normal_threshold == SurfelWarpParams().fusion.normal_threshold
    metrics = run(seq, tmp_path / "out", "--max-frames", 3, "--config", cfg)
    method = metrics["config"]["method"]
    assert method["fusion"]["distance_threshold_m"] == 0.005 and method["tracking"]["nonrigid"]["lambda_reg"] == 8.0
    assert method["fusion_enabled"] is True
    assert method["recent_draw"] == "with" and method["tracking"]["hierarchy"]["enabled"] is True
    assert all(f["gauss_newton_iterations"] >= 1 for f in metrics["frames"][1:])


def test_silent_fallbacks_are_counted_per_frame(release, tmp_path):
    """PCG allowed one iteration falls back to LU on every step: metrics.json counts it, frame by
    frame, beside rigid ICP keeping the pose and an aborted reinitialisation (tests/tracking:
    test_tracker.py makes rigid ICP keep the pose)."""
    seq, _ = release
    cfg = tmp_path / "pcg.json"
    cfg.write_text('{"tracking": {"nonrigid": {"pcg_max_iterations": 1}}}')
    frames = run(seq, tmp_path / "out", "--max-frames", 3, "--config", cfg)["frames"]
    assert all(f["lu_fallbacks"] >= f["gauss_newton_iterations"] >= 1 for f in frames[1:])
    assert all(f["rigid_pose_kept"] is False and f["reinit_aborted"] is False for f in frames[1:])
    default = run(seq, tmp_path / "default", "--max-frames", 3)["frames"]
    assert all(f["lu_fallbacks"] == 0 for f in default[1:])


@pytest.mark.parametrize("text, fragment", [
    ('{"fusion": {"distance_treshold_m": 0.01}}', "unknown key"),
    ('{"fusion": {"window": "four"}}', "expected an integer"),
    ('{"tracking": {"nonrigid": {"robust": "cauchy"}}}', "expected one of"),
    ('{"fusion": 3}', "expected a table"),
    ('{"fusion": {"window": 0}}', "'fusion.window': must be in (0, 16], got 0"),
    ('{"warp_field": {"sigma_m": 0}}', "'warp_field.sigma_m': must be in (0, 10.0]"),
    ('{"warp_field": {"node_radius_m": 1e300}}', "'warp_field.node_radius_m': must be in (0, 10.0], got 1e+300"),
    ('{"tracking": {"nonrigid": {"max_step_m": 11}}}', "'tracking.nonrigid.max_step_m': must be in (0, 10.0], got 11"),
    ('{"fusion": {"normal_threshold": 1.5}}', "'fusion.normal_threshold': must be in [0, 1], got 1.5"),
    ('{"tracking": {"rigid": {"distance_gate_m": [0.1, 0, 0.02]}}}', "'tracking.rigid.distance_gate_m': must be in"),
    ('{"tracking": {"nonrigid": {"feature_weight": 0}}}', None),
    ('{"recent_draw": "sometimes"}', "expected one of"),
    ('{"tracking": {"hierarchy": {"levels": 0}}}', "'tracking.hierarchy.levels': must be in (0, 8]"),
    ('{"tracking": {"hierarchy": {"beta": 0}}}', "'tracking.hierarchy.beta': must be in (0, inf)"),
    ('{"tracking": {"nonrigid": {"terms": ["depth", "no_such_term"]}}}', "unknown term(s) no_such_term"),
    ("{not json", "does not parse"),
])
def test_bad_config_is_one_clear_error(tmp_path, text, fragment):
    cfg = tmp_path / "bad.json"
    cfg.write_text(text)
    if fragment is None:      # 0 is meaningful here (a weight that turns a term off)
        load_params(cfg, SurfelWarpParams())
        return
    with pytest.raises(InputError) as err:
        load_params(cfg, SurfelWarpParams())
    assert fragment in str(err.value) and "bad.json" in str(err.value)


def test_bad_config_from_the_cli_exits_2_and_writes_nothing(release, tmp_path):
    seq, _ = release
    cfg = tmp_path / "bad.json"
    cfg.write_text('{"fusion": {"distance_treshold_m": 0.01}}')
    out = tmp_path / "out"
    for extra in ([], ["--method", "dynamicfusion"]):
        proc = subprocess.run([sys.executable, "-m", "surfelwarp", "run", str(seq), "--out", str(out),
                               "--config", str(cfg), *extra], capture_output=True, text=True)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and "bad.json" in proc.stderr
    assert not out.exists()


@pytest.mark.slow
def test_rest_anchors_keep_a_static_scene_from_drifting(tmp_path):
    """A still life seen by an orbiting camera: under the k-nearest-node graph alone (the
    papers' pipeline: anchors off, rigid ICP by least squares over every pixel, no free-space
    term, appending and fusion as in the paper) the field slowly bends along the wide bends
    the graph barely resists, and the pose drifts with it. Rest anchors (the default) hold the
    nodes nothing moves; DynamicFusion's tree on top of the graph
    (tracking.hierarchy.keep_graph) resists the bends. Since the pose takes from the field only
    what the depth pairs measure (Tracker.factor), the graph's pose drifts half as far as
    before (ATE 0.62 -> 0.29 cm; anchored 0.21 -> 0.16, tree 0.16 -> 0.15), so the anchors'
    and the tree's gain over it fell from 3-4x to ~2x."""
    seq = synth.generate("orbit", tmp_path / "seq", frames=40, size=(320, 240))
    # Depth alone, the subject here: colour matches carry a viewpoint bias of their own (a
    # still life seen 10 degrees apart: 0.3-0.5 mm) that releases anchors (README, Colour).
    depth_only = tmp_path / "depth.toml"
    depth_only.write_text("[tracking.nonrigid]\nfeature_weight = 0.0\n")
    off = "[tracking.anchor]\nweight = 0.0\n[tracking.nonrigid]\nfeature_weight = 0.0\n"
    graph, tree = tmp_path / "graph.toml", tmp_path / "tree.toml"
    graph.write_text(off + "[tracking]\nreleased_rigid_weight = 1.0\n[tracking.rigid]\nmin_eigen_ratio = 0.0\n"
                           "weak_eigen_ratio = 0.0\n[tracking.nonrigid.silhouette]\nweight = 0.0\n"
                           "[fusion]\ncarve_beyond_m = 1e9\nappend_only_uncovered = false\n"
                           "reference_along_normal = false\n")
    tree.write_text(off + "[tracking.hierarchy]\nenabled = true\nkeep_graph = true\n")
    ate = {}
    for name, flags in (("graph", ("--config", graph)), ("anchored", ("--config", depth_only)),
                        ("tree", ("--config", tree))):
        frames = run(seq, tmp_path / name, "--save-every", 1000, *flags)["frames"]
        ate[name] = evaluate.evaluate(tmp_path / name, seq)["trajectory"]["ate_cm"]
        if name == "anchored":     # the scene is still: nearly every node stays anchored
            assert all(f["released_nodes"] < 0.1 * f["nodes"] for f in frames[1:])
        else:
            assert "released_nodes" not in frames[-1]
    print("orbit, 40 frames, ATE: " + ", ".join(f"{k} {v:.2f} cm" for k, v in ate.items()))
    assert ate["graph"] < 0.45          # 0.62 with the field's common motion fitted whole
    assert ate["anchored"] < 0.25 and ate["anchored"] < 0.75 * ate["graph"]
    assert ate["tree"] < 0.25 and ate["tree"] < 0.75 * ate["graph"]
