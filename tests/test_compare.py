import argparse
import json

import cv2
import numpy as np
import pytest

from surfelwarp.compare import (METHODS, CompareSpec, add_arguments, compare, input_normals, normal_colours,
                                render_live_normals, spec_from_args)
from surfelwarp.data_tools import synth
from surfelwarp.dynamicfusion import DynamicFusionParams
from surfelwarp.errors import InputError
from surfelwarp.sequence import open_sequence
from surfelwarp.tsdf import TSDFParams

FAST_DF = DynamicFusionParams(tsdf=TSDFParams(voxel_size_m=0.008, truncation_m=0.024))


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    seq = synth.generate("sheet", root / "sheet", frames=6, size=(320, 240))
    spec = CompareSpec(input=seq, out=root / "out", save_every=2, dynamicfusion=FAST_DF)
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


def test_normal_renders_match_the_observed_normals(compared):
    seq_dir, spec, _ = compared
    seq = open_sequence(seq_dir)
    observed = input_normals(seq, 5, spec.preprocess)
    seen = np.any(observed < 1, axis=-1)
    for name in METHODS:
        image = render_live_normals(spec.out / name / "live" / "frame-000005.ply", seq.intrinsics)
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
    args = parser.parse_args([str(tmp_path / "missing"), "--out", str(tmp_path / "o"), "--max-frames", "3",
                              "--voxel-size", "0.01", "--hierarchical", "--clip-far", "2", "--render-frames", "1,2"])
    spec = spec_from_args(args)
    assert spec.max_frames == 3 and spec.preprocess.clip_far_m == 2.0 and args.render_frames == [1, 2]
    assert spec.dynamicfusion.tsdf.voxel_size_m == 0.01 and spec.dynamicfusion.tsdf.truncation_m == pytest.approx(0.03)
    assert spec.dynamicfusion.hierarchical_graph
    with pytest.raises(InputError, match="does not exist"):
        compare(spec)
    assert not (tmp_path / "o").exists()
