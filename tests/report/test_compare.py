import argparse
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from surfelwarp.cli import _add_compare_arguments as add_arguments
from surfelwarp.cli import compare_spec as spec_from_args
from surfelwarp.data_tools import synth
from surfelwarp.errors import InputError
from surfelwarp.io.sequence import open_sequence
from surfelwarp.methods.dynamicfusion.params import DynamicFusionParams
from surfelwarp.methods.dynamicfusion.tsdf import TSDFParams
from surfelwarp.report.compare import compare
from surfelwarp.report.contact import contact_gaps, phase_averages, topology_phases
from surfelwarp.report.document import speed_lines, surfelwarp_variant
from surfelwarp.report.metrics import speed
from surfelwarp.report.renders import input_normals, normal_colours, render_live
from surfelwarp.report.runner import METHODS, CompareSpec

pytestmark = pytest.mark.slow     # end-to-end runs

FAST_DF = DynamicFusionParams(tsdf=TSDFParams(voxel_size_m=0.008, truncation_m=0.024))


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    seq = synth.generate("sheet", root / "sheet", frames=6, size=(320, 240))
    # SurfelWarp as template tracking: fast, and the comparison machinery is what is tested here.
    spec = CompareSpec(input=seq, out=root / "out", save_every=2, dynamicfusion=FAST_DF, surfelwarp_fusion=False)
    return seq, spec, compare(spec)


def test_compare_runs_both_methods_and_writes_the_report(compared):
    seq, spec, report = compared
    out = spec.out
    assert report == out / "report.md"
    for name in ("timing", "model_size", "memory", "accuracy"):
        image = cv2.imread(str(out / f"{name}.png"))
        assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    renders = sorted(p.name for p in out.glob("normals-*.png"))
    assert renders == ["normals-000000.png", "normals-000004.png", "normals-000005.png"]
    text = report.read_text()
    for piece in ("| | SurfelWarp | DynamicFusion |", "](timing.png)", "](model_size.png)", "](memory.png)",
                  "](accuracy.png)", "](normals-000005.png)", "accuracy, median (mm)", "EPE, mean (mm)"):
        assert piece in text
    metrics = {n: json.loads((out / n / "metrics.json").read_text()) for n in METHODS}
    assert [metrics[n]["method"] for n in METHODS] == list(METHODS)
    assert all(len(metrics[n]["frames"]) == 6 for n in METHODS)
    sw, df = (metrics[n]["frames"][-1] for n in METHODS)
    # The volumetric model is larger: more elements and more bytes than the surfels.
    assert df["voxels"] > 10 * sw["surfels"] > 0 and df["model_bytes"] > 5 * sw["model_bytes"] > 0
    for n in METHODS:
        ev = json.loads((out / n / "eval.json").read_text())
        assert ev["average"]["accuracy_median_mm"] < 2.0
        # The table shows the same figure as eval.json.
        assert f"{ev['average']['accuracy_median_mm']:.2f}" in text.split("accuracy, median (mm)")[1].split("\n")[0]
    rows = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ")}
    assert "voxels (last frame)" in rows and f"| {df['voxels']} |" in rows["voxels (last frame)"]
    # The speed ratio is stated, from the medians of the frames after the first, with the variant.
    totals = {n: np.median([f["seconds"]["total"] for f in metrics[n]["frames"][1:]]) for n in METHODS}
    ratio = totals["dynamicfusion"] / totals["surfelwarp"]
    model_ratio = speed(metrics)["model_ratio"]
    assert f"**Speed ratio: SurfelWarp is {ratio:.2f}x faster per frame than DynamicFusion, " \
           f"{model_ratio:.2f}x in the model update**" in text
    assert metrics["surfelwarp"]["config"]["method"]["fusion_enabled"] is False
    assert "SurfelWarp ran as template tracking (`fusion=False`" in text
    assert "Warp field of both: nodes 25 mm apart, 4 skinning and 8 regularisation neighbours." in text
    # DynamicFusion warped only the voxels that could be fused, and fused some of each.
    for f in metrics["dynamicfusion"]["frames"][1:]:
        assert 0 < f["fused_voxels"] <= f["warped_voxels"] < f["voxels"]


def test_normal_renders_match_the_observed_normals(compared):
    seq_dir, spec, _ = compared
    seq = open_sequence(seq_dir)
    observed = input_normals(seq, 5, spec.preprocess)
    seen = np.any(observed < 1, axis=-1)
    for name in METHODS:
        image = render_live(spec.out / name / "live" / "frame-000005.ply", seq.intrinsics)
        drawn = np.any(image < 1, axis=-1)
        both = seen & drawn
        assert both.sum() / (seen | drawn).sum() > 0.85, name
        # Colours encode normals: the model's agree with the depth's within a few degrees.
        assert np.median(np.abs(image[both] - observed[both])) < 0.05, name


def test_normal_colours():
    n = np.array([[[0, 0, -1], [1, 0, 0]]], np.float32)
    rgb = normal_colours(n, np.array([[True, False]]))
    np.testing.assert_allclose(rgb[0, 0], [0.5, 0.5, 1.0])
    np.testing.assert_allclose(rgb[0, 1], [1.0, 1.0, 1.0])


def test_arguments_and_bad_input(tmp_path):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    spec = spec_from_args(parser.parse_args([str(tmp_path / "missing"), "--out", str(tmp_path / "o")]))
    assert spec.surfelwarp_fusion and spec.surfelwarp_warp_field is None
    args = parser.parse_args([str(tmp_path / "missing"), "--out", str(tmp_path / "o"), "--max-frames", "3",
                              "--voxel-size", "0.01", "--hierarchical", "--clip-far", "2", "--render-frames", "1,2",
                              "--no-fusion", "--graph-k", "4"])
    spec = spec_from_args(args)
    assert not spec.surfelwarp_fusion
    assert spec.surfelwarp_warp_field.graph_k == spec.dynamicfusion.warp_field.graph_k == 4
    assert spec.max_frames == 3 and spec.preprocess.clip_far_m == 2.0 and args.render_frames == [1, 2]
    assert spec.dynamicfusion.tsdf.voxel_size_m == 0.01 and spec.dynamicfusion.tsdf.truncation_m == pytest.approx(0.03)
    assert spec.dynamicfusion.tracking.hierarchy.enabled
    with pytest.raises(InputError, match="does not exist"):
        compare(spec)
    assert not (tmp_path / "o").exists()


def test_cli_rejects_bad_input_with_status_2(tmp_path):
    def run(*args):
        proc = subprocess.run([sys.executable, "-m", "surfelwarp", "compare", *map(str, args)],
                              capture_output=True, text=True)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        return proc.stderr

    out = tmp_path / "out"
    (tmp_path / "empty").mkdir()
    assert str(tmp_path / "empty") in run(tmp_path / "empty", "--out", out)      # no known layout
    assert "--voxel-size must be in (0, 1) metres" in run(tmp_path / "missing", "--out", out, "--voxel-size", "-1")
    (tmp_path / "file").write_text("x")
    assert "not a folder" in run(tmp_path / "empty", "--out", tmp_path / "file")
    assert not out.exists()


def fake_metrics(seconds: dict[str, dict[str, float]], fusion=False) -> dict:
    frames = lambda s: [{"frame": i, "seconds": {**s, "total": sum(s.values())}} for i in range(3)]  # noqa: E731
    return {"surfelwarp": {"config": {"method": {"fusion_enabled": fusion}}, "frames": frames(seconds["surfelwarp"])},
            "dynamicfusion": {"config": {"method": {}}, "frames": frames(seconds["dynamicfusion"])}}


def test_speed_splits_tracking_from_the_model_update():
    metrics = fake_metrics({"surfelwarp": {"read": 0.01, "preprocess": 0.04, "solver_maps": 0.05, "rigid": 0.05,
                                           "nonrigid": 0.2, "warp": 0.01},
                            "dynamicfusion": {"read": 0.01, "preprocess": 0.04, "solver_maps": 0.02, "rigid": 0.05,
                                              "predict": 0.03, "nonrigid": 0.15, "warp": 0.2, "fusion": 0.05}})
    sp = speed(metrics)
    assert sp["surfelwarp"] == pytest.approx({"total": 360, "input": 50, "tracker": 300, "model": 10})
    assert sp["dynamicfusion"] == pytest.approx({"total": 550, "input": 50, "tracker": 250, "model": 250})
    assert sp["ratio"] == pytest.approx(550 / 360) and sp["ratio_bound"] == pytest.approx(550 / 350)
    assert sp["model_ratio"] == pytest.approx(25)
    # a saved frame's outputs (live PLY, picture) are inside its total, but no model update
    saved = fake_metrics({"surfelwarp": {"read": 0.01, "preprocess": 0.04, "solver_maps": 0.05, "rigid": 0.05,
                                         "nonrigid": 0.2, "warp": 0.01, "write": 0.02, "render": 0.03},
                          "dynamicfusion": {"read": 0.01}})
    assert speed(saved)["surfelwarp"] == pytest.approx({"total": 410, "input": 50, "tracker": 300, "model": 10})
    text = "\n".join(speed_lines(metrics))
    assert "SurfelWarp is 1.53x faster per frame than DynamicFusion, 25.00x in the model update" in text
    assert "at most 1.57x faster" in text and "template tracking" in text and "| model update (all other stages but the outputs) | 10 | 250 | 25.00x |" in text
    metrics["surfelwarp"]["config"]["method"]["fusion_enabled"] = True
    assert "surfel fusion (`fusion=True`)" in "\n".join(speed_lines(metrics))
    assert "unknown variant" in surfelwarp_variant({"config": {"method": {"fusion": {"max_weight": 1}}}})


def test_touch_ground_truth_gives_the_contact_phases(tmp_path):
    seq = synth.generate("touch", tmp_path / "touch", frames=48, size=(32, 24))
    frames, gap = contact_gaps(seq)
    assert list(frames) == list(range(48))
    # Open: the fingers' surfaces are 2 x 2 cm apart; they touch around frame 30 (x = 0.5).
    assert gap[0] == pytest.approx(40, abs=0.5) and gap[30] < 0.05
    phases = topology_phases(frames, gap)
    contact = phases["in contact"]
    assert contact == list(range(contact[0], contact[-1] + 1)) and 19 <= contact[0] <= 23 and 37 <= contact[-1] <= 41
    assert phases["before contact"] == list(range(contact[0]))
    assert phases["after separation"] == list(range(contact[-1] + 1, 48))
    assert all(gap[f] < 1.0 for f in contact) and all(gap[f] >= 1.0 for f in phases["after separation"])
    # One rigid part only, or parts that never touch: no topology change.
    assert topology_phases(frames, gap + 5.0) is None
    assert contact_gaps(synth.generate("sheet", tmp_path / "sheet", frames=2, size=(32, 24))) is None
    results = {n: {"frames": [{"frame": f, "accuracy_median_mm": f + k, "epe_mean_mm": None} for f in range(0, 48, 6)]}
               for k, n in enumerate(METHODS)}
    avg = phase_averages(results, phases)
    after = [f for f in range(0, 48, 6) if f in phases["after separation"]]
    assert avg["after separation"]["surfelwarp"]["frames"] == after
    assert avg["after separation"]["dynamicfusion"]["accuracy_median_mm"] == pytest.approx(np.mean(after) + 1)
    assert avg["after separation"]["surfelwarp"]["epe_mean_mm"] is None
