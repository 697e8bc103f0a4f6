"""`surfelwarp bench SEQ`: where a frame's time goes, stage by stage, and how it grows with the model.

SurfelWarp (and with --compare-with dynamicfusion the baseline, on the same frames) runs in a
fresh process as `compare` runs it; from its metrics.json the benchmark prints, as markdown:
per-stage medians (frames after the first, which only initialises), ms per 100k surfels of
every stage at three model sizes (the frames in thirds by surfel count; one size if the thirds
are alike), bytes per surfel of the whole surfel model (surfel arrays and warp field), the
colour stage's share of a frame (where colour features were matched; with --colour-cost also
everything colour adds, against SurfelWarp run again without it), and the ratios
DynamicFusion / SurfelWarp per frame and in the model update (every stage after the shared
tracker but a saved frame's outputs). With --open3d, Open3D's dense SLAM
(open3d.t.pipelines.slam on the CPU, depth only) tracks and fuses the same frames as a
reference for what a compiled CPU pipeline does per frame.

The machine is shared and noisy: compare ratios measured in one run, not times across runs.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surfelwarp.report.document import speed_lines
from surfelwarp.report.metrics import load_metrics, speed, stage_seconds
from surfelwarp.report.runner import LABELS, CompareSpec, open_input, run_in_child

MEMORY_TARGET_BYTES = 208      # per surfel: the CUDA original's double buffer
OPEN3D_VOXEL_M = 0.0058        # as in the measurement on 7-Scenes


@dataclass(frozen=True)
class Open3DResult:
    median_frame_ms: float
    frames: int
    voxel_m: float


def _after_first(metrics: dict) -> tuple[slice, dict[str, np.ndarray], np.ndarray]:
    """The frames after the first (which only initialises; all of one frame), every stage's
    seconds over all frames and the frame totals over those after the first."""
    frames, seconds = stage_seconds(metrics)
    later = slice(1, None) if len(frames) > 1 else slice(None)
    return later, seconds, np.array([f["seconds"]["total"] for f in metrics["frames"]])[later]


SAME_SIZE = 1.05     # thirds of the run whose model sizes are within this ratio are one size


def stage_table(metrics: dict) -> list[str]:
    """Per-stage median ms, and ms per 100k surfels at three model sizes (SurfelWarp only; one
    size if the model stayed within SAME_SIZE of one)."""
    later, seconds, totals = _after_first(metrics)
    surfels = np.array([f.get("surfels") or 0 for f in metrics["frames"]], float)[later]
    thirds = [t for t in np.array_split(np.argsort(surfels, kind="stable"), 3) if len(t)] if surfels.any() else []
    sizes = [np.median(surfels[t]) for t in thirds]
    if thirds and max(sizes) <= SAME_SIZE * max(min(sizes), 1):
        thirds = [np.concatenate(thirds)]      # a model that does not grow has one size, not three
    head = "| stage | median ms |" + "".join(f" ms/100k surfels at {np.median(surfels[t]) / 1000:.0f}k |"
                                           for t in thirds)
    lines = [head, "|---|---:|" + "---:|" * len(thirds)]
    ahead = stage_seconds(metrics, "ahead_seconds")[1]
    rows = list(seconds.items()) + [("total", totals)] + [(f"{k}, read ahead", v) for k, v in ahead.items()]
    for stage, s in rows:
        s = s if stage == "total" else s[later]
        if not s.any():
            continue
        per = "".join(f" {1e5 * np.median(1000 * s[t] / np.maximum(surfels[t], 1)):.1f} |" for t in thirds)
        lines.append(f"| {stage} | {1000 * np.median(s):.1f} |{per}")
    if ahead:
        lines += ["", "The stages above `total` are what a frame waited for; those read ahead ran on the read-ahead "
                      "worker while the frame before was processed (`ahead`: free space and colour features)."]
    return lines


def memory_line(metrics: dict) -> str | None:
    last = metrics["frames"][-1]
    if not last.get("surfels") or not last.get("model_bytes"):
        return None
    per = last["model_bytes"] / last["surfels"]
    verdict = "within" if per <= MEMORY_TARGET_BYTES else "above"
    return (f"Model memory: {last['model_bytes'] / 2 ** 20:.1f} MiB for {last['surfels']} surfels and "
            f"{last.get('nodes', 0)} nodes, **{per:.0f} bytes per surfel** ({verdict} the "
            f"{MEMORY_TARGET_BYTES}-byte target); peak RSS {metrics['summary']['peak_rss_mb']:.0f} MiB.")


COLOUR_TARGET_SHARE = 0.2      # of a frame, for the colour terms (issue 19)


def colour_line(metrics: dict) -> str | None:
    """The colour stage's median share of the frame (frames after the first), if colour
    features were matched (feature_matches in metrics.json; none without colour, or with the
    feature term off). It leaves out what colour adds to the other stages: the feature term in
    the non-rigid solve, the colour pairs in rigid ICP, the colour image's reading and fusion.
    On twist-limb at a2427a6 (40 frames) a frame took 945 ms with colour and 612 without: the
    stage 252 ms (27 %), everything colour adds 333 ms (35 %)."""
    later, seconds, totals = _after_first(metrics)
    features = seconds.get("features")
    if features is None or all(f.get("feature_matches") is None for f in metrics["frames"]):
        return None
    features = features + seconds.get("ahead", 0.0)       # and the wait for what was found ahead
    share = float(np.median(features[later] / np.maximum(totals, 1e-12)))
    verdict = "within" if share <= COLOUR_TARGET_SHARE else "above"
    early = stage_seconds(metrics, "ahead_seconds")[1].get("ahead")
    early = "" if early is None else (f" Done ahead, on the read-ahead worker while the frame before ran (the "
                                      f"features, their matches with the last frame and the keyframe, and the "
                                      f"free space): {1000 * np.median(early[later]):.0f} ms more.")
    return (f"Colour: the `features` stage (detection, matching, flow, refinement, checks) takes "
            f"{1000 * np.median(features[later]):.0f} ms, **{100 * share:.1f} % of a frame** (median; {verdict} "
            f"the {100 * COLOUR_TARGET_SHARE:.0f} % target).{early} Not counted: the feature term in the non-rigid "
            f"solve and the colour pairs in rigid ICP (`--colour-cost` times all colour adds).")


def colour_cost_line(with_colour: dict, without: dict) -> str:
    """Everything colour adds to a frame: the median frame of a run with colour against that of
    the same frames run with the feature term off (the colour still read and fused into the
    surfels, but not matched nor used by the tracker), and the stages that grew most. Each run
    follows its own solution, so a stage's growth includes the work colour changes (a
    Gauss-Newton iteration more where it moves the solve); the read-ahead worker's colour work
    counts where a frame waits for it or loses the cores to it."""
    later, grown, totals = _after_first(with_colour)
    _, off, totals_off = _after_first(without)
    a, b = float(np.median(totals)), float(np.median(totals_off))
    share = (a - b) / max(a, 1e-12)
    verdict = "within" if share <= COLOUR_TARGET_SHARE else "above"
    growth = [(1000 * (np.median(s[later]) - (np.median(off[stage][later]) if stage in off else 0.0)), stage)
              for stage, s in grown.items()]
    most = ", ".join(f"`{stage}` +{g:.0f}" for g, stage in sorted(growth, reverse=True)[:4] if g >= 0.5)
    grew_most = f"; the stages that grew most (median ms): {most}." if most else "."
    return (f"Colour, all it adds: a frame takes {1000 * a:.0f} ms with colour and {1000 * b:.0f} ms with the "
            f"feature term off (colour read and fused, not matched), so colour is **{100 * share:.1f} % of a "
            f"frame** ({verdict} the {100 * COLOUR_TARGET_SHARE:.0f} % target){grew_most}")


def run_open3d(spec: CompareSpec, voxel_m: float = OPEN3D_VOXEL_M) -> Open3DResult:
    """Open3D's dense SLAM on the spec's frames (depth only: the colour is a constant); ImportError
    when open3d is not installed."""
    import open3d as o3d
    import open3d.core as o3c

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)   # no colour: warns every frame
    seq = open_input(spec)
    K = seq.intrinsics
    device = o3c.Device("CPU:0")
    intrinsic = o3c.Tensor([[K.fx, 0, K.cx], [0, K.fy, K.cy], [0, 0, 1]], o3c.Dtype.Float64)
    slam = o3d.t.pipelines.slam
    model = slam.Model(voxel_m, 16, 40000, o3c.Tensor(np.eye(4)), device)
    frame, raycast = slam.Frame(K.height, K.width, intrinsic, device), slam.Frame(K.height, K.width, intrinsic, device)
    grey = o3d.t.geometry.Image(o3c.Tensor(np.full((K.height, K.width, 3), 128, np.uint8)))
    scale, near, far = 1000.0, spec.preprocess.clip_near_m, spec.preprocess.clip_far_m
    T = o3c.Tensor(np.eye(4))
    seconds = []
    for i, (_, depth_m) in enumerate(seq.frames()):
        t0 = time.perf_counter()
        depth = np.where((depth_m >= near) & (depth_m <= far), depth_m * scale, 0).astype(np.uint16)
        frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(depth)))
        frame.set_data_from_image("color", grey)
        if i > 0:
            result = model.track_frame_to_model(frame, raycast, scale, far, 0.07)
            T = T @ result.transformation
        model.update_frame_pose(i, T)
        model.integrate(frame, scale, far, 8.0)
        model.synthesize_model_frame(raycast, scale, near, far, 8.0, False)
        seconds.append(time.perf_counter() - t0)
    later = seconds[1:] or seconds
    return Open3DResult(1000 * float(np.median(later)), len(seconds), voxel_m)


def _try_open3d(spec: CompareSpec) -> Open3DResult | ImportError:
    try:
        return run_open3d(spec)
    except ImportError as exc:
        return exc


def open3d_line(o3: list, surfelwarp_ms: float) -> str:
    """The report's line on Open3D's runs before and after SurfelWarp's (or the ImportError)."""
    if isinstance(o3[0], ImportError):
        return (f"Open3D is not available ({o3[0]}): `pip install 'surfelwarp[bench]'` installs open3d-cpu, "
                "which also needs the system's libusb-1.0-0.")
    before, after = o3
    mean = 0.5 * (before.median_frame_ms + after.median_frame_ms)
    return (f"Open3D (CPU, depth only, {1000 * before.voxel_m:.1f} mm voxels): {before.median_frame_ms:.0f} ms per "
            f"frame before SurfelWarp's run and {after.median_frame_ms:.0f} ms after ({before.frames} frames each); "
            f"SurfelWarp {surfelwarp_ms:.0f} ms, **{surfelwarp_ms / mean:.1f}x Open3D's time** (their mean).")


def bench(spec: CompareSpec, compare_with: str | None = None, open3d: bool = False, colour_cost: bool = False) -> str:
    """Run and report (markdown). The runs go to spec.out, or a temporary folder if it is None;
    with colour_cost and colour features matched, SurfelWarp once more with the feature term
    off, into its `colour-off/` folder."""
    names = ["surfelwarp"] + ([compare_with] if compare_with else [])
    colour_off = None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(spec.out) if spec.out is not None else Path(tmp)
        run_spec = CompareSpec(**{**spec.__dict__, "out": out})
        open_input(run_spec)                      # bad input fails here, before any run
        # Open3D right before and after SurfelWarp's run (ABA), the ratio to their mean: this
        # machine's speed drifts over minutes (7-Scenes, one run after the other: Open3D 195,
        # 206, 225, 253 ms a frame, SurfelWarp within 4 %).
        o3 = [_try_open3d(run_spec)] if open3d else []
        for name in names:
            run_in_child(name, run_spec)
            if name == "surfelwarp" and o3 and not isinstance(o3[0], ImportError):
                o3.append(run_open3d(run_spec))
        metrics = {name: load_metrics(out / name) for name in names}
        colour = colour_line(metrics["surfelwarp"])
        if colour_cost and colour:
            run_in_child("surfelwarp", CompareSpec(**{**run_spec.__dict__, "out": out / "colour-off",
                                                      "surfelwarp_colour": False}))
            colour_off = load_metrics(out / "colour-off" / "surfelwarp")
    lines = [f"# Benchmark of {spec.input}", "", f"{metrics['surfelwarp']['summary']['frames']} frames.", ""]
    for name in names:
        lines += [f"## {LABELS[name]}: stages", "", *stage_table(metrics[name]), ""]
    memory = memory_line(metrics["surfelwarp"])
    if memory:
        lines += [memory, ""]
    if colour:
        lines += [colour, ""]
    if colour_off is not None:
        lines += [colour_cost_line(metrics["surfelwarp"], colour_off), ""]
    elif colour_cost:
        lines += ["Colour, all it adds: nothing to time, no colour features were matched (no colour frames, or "
                  "the feature term is off).", ""]
    if compare_with:
        lines += speed_lines(metrics)
    if open3d:
        sw = speed({"surfelwarp": metrics["surfelwarp"]})["surfelwarp"]["total"]
        lines += ["## Open3D dense SLAM", "", open3d_line(o3, sw), ""]
    return "\n".join(lines)
