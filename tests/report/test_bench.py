"""`surfelwarp bench`: per-stage medians, cost per 100k surfels at three model sizes, bytes per surfel,
the colour stage's share."""
import json
import subprocess
import sys

import pytest

from surfelwarp.data_tools import synth
from surfelwarp.report.bench import Open3DResult, colour_cost_line, colour_line, memory_line, open3d_line, stage_table


def fake_run(surfels, seconds_per_100k):
    """metrics.json of a run whose one model stage costs seconds_per_100k per 100k surfels."""
    frames = [{"frame": i, "surfels": n, "nodes": 10, "model_bytes": 100 * n,
               "seconds": {"read": 0.001, "fuse": seconds_per_100k * n / 1e5,
                           "total": 0.001 + seconds_per_100k * n / 1e5}} for i, n in enumerate(surfels)]
    return {"frames": frames, "summary": {"peak_rss_mb": 50.0}}


def test_stage_table_gives_the_cost_per_100k_surfels_at_three_sizes():
    metrics = fake_run([5_000] + [10_000] * 3 + [20_000] * 3 + [40_000] * 3, 0.03)
    lines = stage_table(metrics)
    assert lines[0] == ("| stage | median ms | ms/100k surfels at 10k | ms/100k surfels at 20k |"
                        " ms/100k surfels at 40k |")
    fuse = next(line for line in lines if line.startswith("| fuse |"))
    assert fuse == "| fuse | 6.0 | 30.0 | 30.0 | 30.0 |"        # the first frame is left out
    assert "| read | 1.0 |" in "\n".join(lines)


def test_a_model_that_does_not_grow_has_one_size():
    lines = stage_table(fake_run([66_000, 66_100, 66_000, 66_300, 66_200, 66_400, 66_500], 0.03))
    assert lines[0] == "| stage | median ms | ms/100k surfels at 66k |"
    assert lines[1] == "|---|---:|---:|"
    assert next(line for line in lines if line.startswith("| fuse |")) == "| fuse | 19.9 | 30.0 |"
    # 5 % apart is still one size; more is three
    columns = [stage_table(fake_run([10_000] + [10_000] * 3 + [10_000 + d] * 3 + [10_000 + 2 * d] * 3, 0.03))[0]
               .count("surfels at") for d in (250, 300)]
    assert columns == [1, 3]


def test_memory_line_states_bytes_per_surfel_against_the_target():
    line = memory_line(fake_run([1000, 2000], 0.01))
    assert "**100 bytes per surfel** (within the 208-byte target)" in line and "2000 surfels" in line
    metrics = fake_run([1000], 0.01)
    metrics["frames"][0]["model_bytes"] = 300_000
    assert "above the 208-byte target" in memory_line(metrics)


def test_colour_line_gives_the_colour_stage_share_of_a_frame():
    metrics = fake_run([1000] * 5, 0.0)
    assert colour_line(metrics) is None                    # no colour: no line
    for f in metrics["frames"]:
        f["seconds"]["features"], f["feature_matches"] = 0.002, None
    assert colour_line(metrics) is None                    # the feature term off: no line either
    for i, f in enumerate(metrics["frames"]):
        f["feature_matches"] = None if i == 0 else 500
        # the first frame (initialisation) is left out; then 25, 30, 10 and 40 % of a frame
        f["seconds"]["features"] = [0.5, 0.025, 0.06, 0.01, 0.08][i]
        f["seconds"]["total"] = [0.5, 0.1, 0.2, 0.1, 0.2][i]
    line = colour_line(metrics)
    assert "**27.5 % of a frame**" in line and "above the 20 % target" in line and "takes 42 ms" in line
    for f in metrics["frames"]:
        f["seconds"]["features"] = 0.1 * f["seconds"]["total"]
    assert "**10.0 % of a frame**" in colour_line(metrics) and "within the 20 % target" in colour_line(metrics)


def test_colour_cost_line_gives_all_colour_adds_against_the_run_without():
    """Known answer: frames of 1.0 s with colour and 0.7 s without are 30 % colour; the stages
    that grew are named by how much (the first frame, which only initialises, left out)."""
    def run(features, nonrigid):
        metrics = fake_run([1000] * 4, 0.0)
        for f in metrics["frames"]:
            f["seconds"].update(features=features, nonrigid=nonrigid, read=0.1)
            f["seconds"]["total"] = features + nonrigid + 0.1
        metrics["frames"][0]["seconds"].update(features=5.0, total=5.0)
        return metrics

    line = colour_cost_line(run(0.25, 0.65), run(0.0, 0.6))
    assert "1000 ms with colour and 700 ms" in line and "**30.0 % of a frame** (above the 20 % target)" in line
    assert "`features` +250, `nonrigid` +50." in line and "`read`" not in line
    line = colour_cost_line(run(0.1, 0.65), run(0.0, 0.6))
    assert "**17.6 % of a frame** (within the 20 % target)" in line
    assert colour_cost_line(run(0.0, 0.6), run(0.0, 0.6)).endswith("(within the 20 % target).")


def test_open3d_line_takes_the_ratio_to_the_runs_before_and_after():
    line = open3d_line([Open3DResult(200.0, 60, 0.0058), Open3DResult(300.0, 60, 0.0058)], 750.0)
    assert "200 ms per frame before SurfelWarp's run and 300 ms after (60 frames each)" in line
    assert "SurfelWarp 750 ms, **3.0x Open3D's time** (their mean)" in line and "5.8 mm voxels" in line
    missing = open3d_line([ImportError("No module named 'open3d'")], 750.0)
    assert missing.startswith("Open3D is not available (No module named 'open3d')") and "surfelwarp[bench]" in missing


@pytest.mark.slow
def test_bench_runs_both_methods_and_prints_the_ratios(tmp_path):
    seq = synth.generate("sheet", tmp_path / "sheet", frames=4, size=(160, 120))
    proc = subprocess.run([sys.executable, "-m", "surfelwarp", "bench", str(seq), "--compare-with", "dynamicfusion",
                           "--open3d", "--colour-cost", "--out", str(tmp_path / "runs")], capture_output=True,
                          text=True)
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    for part in ("## SurfelWarp: stages", "## DynamicFusion: stages", "bytes per surfel", "x in the model update",
                 "| nonrigid |", "## Open3D dense SLAM"):
        assert part in text, text
    assert ("x Open3D's time" in text) or ("Open3D is not available" in text)
    assert (tmp_path / "runs" / "surfelwarp" / "metrics.json").exists()
    # colour: the stage, and all colour adds against SurfelWarp without it (no matches there)
    assert "Colour: the `features` stage" in text and "Colour, all it adds: a frame takes" in text, text
    off = json.loads((tmp_path / "runs" / "colour-off" / "surfelwarp" / "metrics.json").read_text())
    assert all(f.get("feature_matches") is None for f in off["frames"])


def test_bench_rejects_bad_input_with_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    proc = subprocess.run([sys.executable, "-m", "surfelwarp", "bench", str(tmp_path / "empty")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and str(tmp_path / "empty") in proc.stderr
