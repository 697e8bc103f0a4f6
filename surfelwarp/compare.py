"""`surfelwarp compare INPUT --out OUT`: SurfelWarp and the DynamicFusion baseline side by side.

Both methods run on the same frames with the same preprocessing, each in a fresh process (so
each one's peak memory is its own), into OUT/surfelwarp and OUT/dynamicfusion (the outputs
of `surfelwarp run`). Then OUT/report.md is written with PNG plots: time per frame by stage,
model size over frames (surfels vs voxels, and bytes), peak memory, accuracy / completeness /
EPE where the sequence has ground truth (data_tools.evaluate), and normal-map renders of both
live models at a few frames (colour = normal, drawn with the solver-map and mesh-map renderers).
"""
from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
import tempfile
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from .camera import Intrinsics
from .errors import InputError
from .observation import PreprocessParams, preprocess
from .ply import read_ply

METHODS = ("surfelwarp", "dynamicfusion")
NO_GROUND_TRUTH = "no ground truth"


def make_surfelwarp(intrinsics: Intrinsics, warp_field=None, fusion: bool = True):
    """The full pipeline, or template tracking with fusion=False; warp_field: WarpFieldParams
    replacing SurfelWarp's default (None keeps it)."""
    from .pipeline import SurfelWarpMethod, SurfelWarpParams
    params = SurfelWarpParams() if warp_field is None else replace(SurfelWarpParams(), warp_field=warp_field)
    return SurfelWarpMethod(intrinsics, params, fusion=fusion)


def surfelwarp_variant(metrics: dict) -> str:
    """Which SurfelWarp ran, from its metrics.json config."""
    fusion = metrics.get("config", {}).get("method", {}).get("fusion_enabled")
    if fusion is False:
        return ("template tracking (`fusion=False`: the first frame's surfels tracked, never fused, "
                "extended or reinitialised)")
    if fusion is True:
        return "the full pipeline with surfel fusion (`fusion=True`)"
    return "an unknown variant (its metrics.json has no boolean `fusion_enabled`)"


def make_dynamicfusion(intrinsics: Intrinsics, params=None):
    from .dynamicfusion import DynamicFusionMethod, DynamicFusionParams
    return DynamicFusionMethod(intrinsics, params or DynamicFusionParams())


# ---------------------------------------------------------------- running

@dataclass(frozen=True)
class CompareSpec:
    """Everything a run needs, picklable for the child process."""
    input: Path
    out: Path
    intrinsics: Intrinsics | None = None       # None: the sequence's intrinsics file
    depth_scale: float = 1000.0
    start: int = 0
    max_frames: int | None = None
    save_every: int = 10
    preprocess: PreprocessParams = PreprocessParams()
    dynamicfusion: object | None = None        # DynamicFusionParams, None = defaults
    surfelwarp_warp_field: object | None = None  # WarpFieldParams for SurfelWarp, None = its default
    surfelwarp_fusion: bool = True  # False: SurfelWarp as template tracking
    progress: bool | None = False


def surfel_model_bytes(method) -> int:
    """Bytes of a SurfelWarpMethod's model: every surfel array and the warp field."""
    total = sum(getattr(method.model, f.name).nbytes for f in fields(method.model)) if method.model is not None else 0
    if method.field is not None:
        total += method.field.nodes.nbytes + method.field.transforms.nbytes + method.field.graph.nbytes
    return int(total)


class Measured:
    """A method whose frame records also carry `model_bytes` (the memory its model holds)."""

    def __init__(self, method):
        self.method, self.name = method, method.name

    def config(self) -> dict:
        return self.method.config()

    def process(self, obs):
        record = self.method.process(obs)
        if "model_bytes" not in record.extra:
            record.extra["model_bytes"] = surfel_model_bytes(self.method)
        return record

    def live_vertices(self):
        return self.method.live_vertices()

    def model_vertices(self):
        return self.method.model_vertices()


def open_input(spec: CompareSpec):
    from .sequence import open_sequence
    return open_sequence(spec.input, intrinsics=spec.intrinsics, depth_scale=spec.depth_scale,
                         start=spec.start, max_frames=spec.max_frames)


def run_method(name: str, spec: CompareSpec) -> tuple[str, str] | None:
    """Run one method into spec.out / name (in the child). Returns (path, problem) of an
    InputError (which does not pickle), else None."""
    from .run import run_sequence
    try:
        seq = open_input(spec)
        if name == "surfelwarp":
            method = make_surfelwarp(seq.intrinsics, spec.surfelwarp_warp_field, spec.surfelwarp_fusion)
        else:
            method = make_dynamicfusion(seq.intrinsics, spec.dynamicfusion)
        input_config = {"layout": seq.layout, "depth_scale": seq.depth_scale, "start": spec.start,
                        "max_frames": spec.max_frames, "intrinsics": {
                            k: getattr(seq.intrinsics, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}}
        run_sequence(seq, spec.out / name, Measured(method), save_every=spec.save_every,
                     preprocess_params=spec.preprocess, input_config=input_config, progress=spec.progress)
    except InputError as exc:
        return (None if exc.path is None else str(exc.path)), exc.problem
    return None


def child_main() -> int:
    """Entry of the child process: argv = [result file]; (name, spec) pickled on stdin."""
    name, spec = pickle.load(sys.stdin.buffer)
    error = run_method(name, spec)
    Path(sys.argv[1]).write_bytes(pickle.dumps(error))
    return 0


def run_in_child(name: str, spec: CompareSpec) -> None:
    """run_method in a fresh interpreter: its peak RSS is that method's alone, and it owns its
    GL context. (A plain subprocess rather than multiprocessing, which would re-import the
    caller's __main__ script.)"""
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.pickle"
        code = "import sys; from surfelwarp.compare import child_main; sys.exit(child_main())"
        proc = subprocess.run([sys.executable, "-c", code, str(result)], input=pickle.dumps((name, spec)))
        if proc.returncode != 0 or not result.exists():
            raise RuntimeError(f"the {name} run failed (exit status {proc.returncode}); see its messages above")
        error = pickle.loads(result.read_bytes())
    if error is not None:
        raise InputError(*error)


# ---------------------------------------------------------------- reading results

def load_metrics(run_dir: Path) -> dict:
    return json.loads((run_dir / "metrics.json").read_text())


def stage_seconds(metrics: dict) -> tuple[list[int], dict[str, np.ndarray]]:
    """Frame numbers and per-stage seconds (0 where a frame lacks the stage), first-seen order."""
    frames = [f["frame"] for f in metrics["frames"]]
    names: list[str] = []
    for f in metrics["frames"]:
        names += [k for k in f["seconds"] if k != "total" and k not in names]
    return frames, {k: np.array([f["seconds"].get(k, 0.0) for f in metrics["frames"]]) for k in names}


def model_counts(metrics: dict) -> dict[str, np.ndarray]:
    """Element counts over frames: surfels, voxels (all / observed) and mesh vertices, if reported."""
    out = {}
    for key in ("surfels", "voxels", "observed_voxels", "mesh_vertices"):
        values = [f.get(key) for f in metrics["frames"]]
        if any(v for v in values):
            out[key] = np.array([v or 0 for v in values], float)
    return out


def evaluate_runs(out: Path, seq_dir: Path) -> dict[str, dict] | None:
    """evaluate() of both runs, or None when the sequence has no ground truth."""
    from .data_tools.evaluate import evaluate
    results = {}
    for name in METHODS:
        try:
            results[name] = evaluate(out / name, seq_dir)
        except InputError as exc:
            if NO_GROUND_TRUTH in exc.problem:
                return None
            raise
    return results


# ---------------------------------------------------------------- speed

INPUT_STAGES = ("read", "preprocess")
# Tracking: the shared rigid ICP and Gauss-Newton, and each method's model maps and data points.
TRACKER_STAGES = ("solver_maps", "rigid", "predict", "nonrigid")


def speed(metrics: dict[str, dict]) -> dict:
    """Median milliseconds per frame (frames after the first, which only initialises) of each
    method: total, input, shared tracker and model update (every other stage), and the ratio
    DynamicFusion / SurfelWarp of the median totals."""
    out = {}
    for name in METHODS:
        frames = metrics[name]["frames"][1:] or metrics[name]["frames"]
        group = lambda f, names: sum(v for k, v in f["seconds"].items() if k in names)  # noqa: E731
        rows = {"total": [f["seconds"]["total"] for f in frames],
                "input": [group(f, INPUT_STAGES) for f in frames],
                "tracker": [group(f, TRACKER_STAGES) for f in frames],
                "model": [f["seconds"]["total"] - group(f, INPUT_STAGES + TRACKER_STAGES) for f in frames]}
        out[name] = {k: 1000 * float(np.median(v)) for k, v in rows.items()}
    sw, df = out["surfelwarp"], out["dynamicfusion"]
    out["ratio"] = df["total"] / sw["total"] if sw["total"] > 0 else float("nan")
    # SurfelWarp can be no faster than its input + tracker, whatever its model update costs.
    out["ratio_bound"] = df["total"] / (sw["input"] + sw["tracker"]) if sw["input"] + sw["tracker"] > 0 else float("nan")
    return out


# ---------------------------------------------------------------- topology change

CONTACT_MM = 1.0   # moving parts closer than this (ground truth) touch


def contact_gaps(seq_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(frames, gap_mm): per frame the smallest surface distance between two different moving
    parts of a synthetic sequence's ground truth; None without ground truth or with fewer than
    two moving parts."""
    path = Path(seq_dir) / "groundtruth.npz"
    if not path.exists():
        return None
    from .data_tools.geometry import TriangleMesh
    from .data_tools.synth import load_groundtruth
    gt = load_groundtruth(seq_dir)
    parts = [p for p in np.unique(gt.part) if gt.moving[gt.part == p].all()]
    if len(parts) < 2:
        return None
    from pykdtree.kdtree import KDTree
    masks = {p: gt.part == p for p in parts}
    faces = {}
    for p, mask in masks.items():
        remap = np.cumsum(mask) - 1
        faces[p] = remap[gt.faces[mask[gt.faces].all(1)]]
    gaps = np.full(len(gt.frames), np.inf)
    for i in range(len(gt.frames)):
        for a in parts:
            va = gt.vertices[i][masks[a]]
            # A point lies at least (distance to the nearest vertex - longest edge) from the
            # mesh: only the points that could beat the nearest one need the exact query.
            edge = np.linalg.norm(va[faces[a]] - va[faces[a][:, [1, 2, 0]]], axis=-1).max()
            tree = KDTree(va)
            for b in parts:
                if b > a:
                    vb = gt.vertices[i][masks[b]]
                    d, _ = tree.query(vb, k=1)
                    near = vb[d <= d.min() + edge]
                    gaps[i] = min(gaps[i], float(TriangleMesh(va, faces[a]).query(near).distance.min()))
    return np.asarray(gt.frames), 1000 * gaps


def topology_phases(frames: np.ndarray, gap_mm: np.ndarray, contact_mm: float = CONTACT_MM) -> dict[str, list[int]] | None:
    """Frames before the first contact, in it, and after the parts separate (until they touch
    again); None if the parts never touch or never part."""
    contact = gap_mm < contact_mm
    if not contact.any() or contact.all():
        return None
    start = int(np.argmax(contact))
    end = start + int(np.argmax(~contact[start:])) if (~contact[start:]).any() else len(contact)
    if end == len(contact):
        return None
    again = end + int(np.argmax(contact[end:])) if contact[end:].any() else len(contact)
    f = [int(x) for x in frames]
    return {"before contact": f[:start], "in contact": f[start:end], "after separation": f[end:again]}


PHASE_KEYS = (("accuracy_median_mm", "accuracy, median (mm)", 2), ("accuracy_mean_mm", "accuracy, mean (mm)", 2),
              ("precision_5mm_pct", "precision at 5 mm (%)", 1), ("completeness_5mm_pct", "completeness at 5 mm (%)", 1),
              ("fscore_5mm_pct", "F-score at 5 mm (%)", 1), ("epe_mean_mm", "EPE, mean (mm)", 1))


def phase_averages(results: dict[str, dict], phases: dict[str, list[int]]) -> dict[str, dict[str, dict]]:
    """phase -> method -> {key: mean over the evaluated frames of that phase, "frames": [...]}."""
    out = {}
    for phase, frames in phases.items():
        out[phase] = {}
        for name in METHODS:
            rows = [r for r in results[name]["frames"] if r["frame"] in set(frames)]
            avg = {"frames": [r["frame"] for r in rows]}
            for key, _, _ in PHASE_KEYS:
                values = [r[key] for r in rows if r.get(key) is not None]
                avg[key] = float(np.mean(values)) if values else None
            out[phase][name] = avg
    return out


def phase_render_frames(out: Path, phases: dict[str, list[int]]) -> list[int]:
    """Saved frames to render: the middle of 'before contact' and 'in contact', and the middle
    and last saved frame 'after separation'."""
    saved = set(pick_frames(out, count=10 ** 6))
    chosen = []
    for phase, picks in (("before contact", (0.5,)), ("in contact", (0.5,)), ("after separation", (0.5, 1.0))):
        frames = [f for f in phases.get(phase, []) if f in saved]
        for q in picks:
            if frames:
                f = frames[min(int(q * len(frames)), len(frames) - 1)]
                if f not in chosen:
                    chosen.append(f)
    return sorted(chosen)


# ---------------------------------------------------------------- normal maps

def normal_colours(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1]: the usual normal-map colouring in a y-up, z-toward-viewer
    frame (a normal facing the camera is light blue); white where mask is False."""
    n = normals * np.array([1.0, -1.0, -1.0], np.float32)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return np.where(mask[..., None], 0.5 + 0.5 * n, 1.0)


def render_live_normals(ply_path: Path, intrinsics: Intrinsics) -> np.ndarray:
    """Normal-map colours of a live PLY: a mesh with mesh maps, surfels with solver maps (disks
    of their radius; a point cloud without radii gets pixel-footprint disks)."""
    from .gl.mesh_maps import render_mesh_maps
    from .gl.solver_maps import render_solver_maps

    table, faces = read_ply(ply_path)
    stack = lambda *names: np.stack([table[n] for n in names], -1).astype(np.float32)  # noqa: E731
    points, normals = stack("x", "y", "z"), stack("nx", "ny", "nz")
    if faces is not None and len(faces):
        maps = render_mesh_maps(points, normals, faces, intrinsics)
    else:
        radius = table["radius"].astype(np.float32) if "radius" in table.dtype.names \
            else np.sqrt(2.0) * points[:, 2] / intrinsics.focal_px
        maps = render_solver_maps(points, normals, radius, intrinsics)
    return normal_colours(maps.normal, maps.index >= 0)


def input_normals(seq, frame: int, params: PreprocessParams) -> np.ndarray | None:
    for i, files in enumerate(seq.files):
        if files.index == frame:
            obs = preprocess(seq.read_depth(files), seq.intrinsics, frame, i, params)
            return normal_colours(obs.normal_map, obs.valid)
    return None


def pick_frames(out: Path, count: int = 3) -> list[int]:
    """Up to `count` evenly spread frames with a live PLY from both methods (the last included)."""
    common = None
    for name in METHODS:
        saved = {int(p.stem.split("-")[1]) for p in (out / name / "live").glob("frame-*.ply")}
        common = saved if common is None else common & saved
    common = sorted(common or ())
    if len(common) <= count:
        return common
    return [common[i] for i in np.linspace(len(common) - 1, 0, count).round().astype(int)[::-1]]


# ---------------------------------------------------------------- plots

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


LABELS = {"surfelwarp": "SurfelWarp", "dynamicfusion": "DynamicFusion"}


def plot_timing(metrics: dict[str, dict], path: Path) -> None:
    plt = _plt()
    stages: list[str] = []
    data = {}
    for name in METHODS:
        data[name] = stage_seconds(metrics[name])
        stages += [s for s in data[name][1] if s not in stages]
    colours = dict(zip(stages, plt.get_cmap("tab20").colors))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for ax, name in zip(axes, METHODS):
        frames, seconds = data[name]
        bottom = np.zeros(len(frames))
        for stage, s in seconds.items():
            ax.bar(frames, s * 1000, bottom=bottom * 1000, width=0.9, color=colours[stage], label=stage)
            bottom += s
        ax.set_title(f"{LABELS[name]}: median {np.median([f['seconds']['total'] for f in metrics[name]['frames']]) * 1000:.0f} ms/frame")
        ax.set_xlabel("frame")
        ax.legend(fontsize=7, ncol=2)
    axes[0].set_ylabel("time per frame (ms)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_model_size(metrics: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, (ax_n, ax_b) = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, style in zip(METHODS, ("-", "--")):
        frames = [f["frame"] for f in metrics[name]["frames"]]
        for key, values in model_counts(metrics[name]).items():
            ax_n.plot(frames, values, style, label=f"{LABELS[name]} {key.replace('_', ' ')}")
        mb = [f.get("model_bytes", 0) / 2 ** 20 for f in metrics[name]["frames"]]
        ax_b.plot(frames, mb, style, label=LABELS[name])
    ax_n.set_yscale("log")
    ax_n.set_ylabel("elements")
    ax_b.set_ylabel("model memory (MiB)")
    ax_b.set_yscale("log")
    for ax in (ax_n, ax_b):
        ax.set_xlabel("frame")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_memory(metrics: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    names = [LABELS[n] for n in METHODS]
    peak = [metrics[n]["summary"]["peak_rss_mb"] for n in METHODS]
    model = [max(f.get("model_bytes", 0) for f in metrics[n]["frames"]) / 2 ** 20 for n in METHODS]
    x = np.arange(len(names))
    ax.bar(x - 0.2, peak, 0.4, label="peak RSS of the run")
    ax.bar(x + 0.2, model, 0.4, label="largest model")
    ax.set_xticks(x, names)
    ax.set_ylabel("MiB")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


ACCURACY_PLOTS = (("accuracy_median_mm", "accuracy, median (mm)"),
                  ("completeness_10mm_pct", "completeness at 1 cm (%)"),
                  ("epe_mean_mm", "end-point error, mean (mm)"))


def plot_accuracy(results: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, len(ACCURACY_PLOTS), figsize=(14, 4))
    for ax, (key, label) in zip(axes, ACCURACY_PLOTS):
        for name, marker in zip(METHODS, ("o-", "s--")):
            rows = results[name]["frames"]
            ax.plot([r["frame"] for r in rows], [np.nan if r[key] is None else r[key] for r in rows],
                    marker, label=LABELS[name])
        ax.set_title(label)
        ax.set_xlabel("frame")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_topology(results: dict[str, dict], frames: np.ndarray, gap_mm: np.ndarray, phases: dict[str, list[int]],
                  path: Path) -> None:
    plt = _plt()
    panels = (("gap", "gap between the parts, ground truth (mm)"),
              ("accuracy_mean_mm", "accuracy, mean (mm)"),
              ("precision_5mm_pct", "precision at 5 mm (%)"),
              ("epe_mean_mm", "end-point error, mean (mm)"))
    fig, axes = plt.subplots(1, len(panels), figsize=(18, 4))
    contact = phases["in contact"]
    for ax, (key, label) in zip(axes, panels):
        ax.axvspan(contact[0] - 0.5, contact[-1] + 0.5, color="0.85", label="in contact")
        if key == "gap":
            ax.plot(frames, gap_mm, "k-")
        else:
            for name, marker in zip(METHODS, ("o-", "s--")):
                rows = results[name]["frames"]
                ax.plot([r["frame"] for r in rows], [np.nan if r[key] is None else r[key] for r in rows],
                        marker, label=LABELS[name])
            ax.legend(fontsize=8)
        ax.set_title(label)
        ax.set_xlabel("frame")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def crop_to_content(panels: list[tuple[str, np.ndarray]], margin_px: int = 12) -> list[tuple[str, np.ndarray]]:
    """The panels cut to the box (plus a margin) holding every panel's non-white pixels."""
    drawn = np.any([np.any(image < 1.0, axis=-1) for _, image in panels], axis=0)
    if not drawn.any():
        return panels
    rows, cols = np.flatnonzero(drawn.any(1)), np.flatnonzero(drawn.any(0))
    r0, r1 = max(rows[0] - margin_px, 0), rows[-1] + margin_px + 1
    c0, c1 = max(cols[0] - margin_px, 0), cols[-1] + margin_px + 1
    return [(label, image[r0:r1, c0:c1]) for label, image in panels]


def plot_normals(panels: list[tuple[str, np.ndarray]], title: str, path: Path) -> None:
    plt = _plt()
    panels = crop_to_content(panels)
    h, w = panels[0][1].shape[:2]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.2 * h / w + 0.6))
    for ax, (label, image) in zip(np.atleast_1d(axes), panels):
        ax.imshow(image)
        ax.set_title(label)
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---------------------------------------------------------------- report

def _fmt(value, digits=1) -> str:
    return "-" if value is None or (isinstance(value, float) and not np.isfinite(value)) else f"{value:.{digits}f}"


def summary_rows(metrics: dict[str, dict], results: dict[str, dict] | None) -> list[tuple[str, ...]]:
    rows = []

    def row(label, fn, digits=1):
        rows.append((label, *(_fmt(fn(n), digits) for n in METHODS)))

    def median_stage(name, stage):
        values = [f["seconds"][stage] for f in metrics[name]["frames"][1:] if stage in f["seconds"]]
        return 1000 * float(np.median(values)) if values else None

    row("frames", lambda n: metrics[n]["summary"]["frames"], 0)
    row("first frame (ms)", lambda n: 1000 * metrics[n]["frames"][0]["seconds"]["total"], 0)
    row("median time per frame (ms)", lambda n: 1000 * metrics[n]["summary"]["median_frame_seconds"], 0)
    stages = []
    for n in METHODS:
        stages += [s for s in stage_seconds(metrics[n])[1]
                   if s not in stages and any(s in f["seconds"] for f in metrics[n]["frames"][1:])]
    for stage in stages:
        row(f"  {stage} (ms, median after frame 1)", lambda n, s=stage: median_stage(n, s), 1)
    last = {n: metrics[n]["frames"][-1] for n in METHODS}
    row("surfels (last frame)", lambda n: last[n].get("surfels") or None, 0)
    row("voxels (last frame)", lambda n: last[n].get("voxels"), 0)
    row("mesh vertices (last frame)", lambda n: last[n].get("mesh_vertices"), 0)
    row("nodes (last frame)", lambda n: last[n].get("nodes"), 0)
    row("model memory, last frame (MiB)", lambda n: last[n].get("model_bytes", 0) / 2 ** 20, 1)
    row("peak RSS (MiB)", lambda n: metrics[n]["summary"]["peak_rss_mb"], 0)
    if results:
        avg = {n: results[n]["average"] for n in METHODS}
        row("accuracy, median (mm)", lambda n: avg[n].get("accuracy_median_mm"), 2)
        row("completeness at 5 mm (%)", lambda n: avg[n].get("completeness_5mm_pct"), 1)
        row("completeness at 1 cm (%)", lambda n: avg[n].get("completeness_10mm_pct"), 1)
        row("F-score at 5 mm (%)", lambda n: avg[n].get("fscore_5mm_pct"), 1)
        row("normal consistency", lambda n: avg[n].get("normal_consistency"), 3)
        row("EPE, mean (mm)", lambda n: avg[n].get("epe_mean_mm"), 1)
        row("EPE under 2 cm (%)", lambda n: avg[n].get("epe_under_2cm_pct"), 1)
        row("ATE (cm)", lambda n: results[n]["trajectory"].get("ate_cm"), 2)
    return rows


SPEED_TARGET = 3.0   # SurfelWarp should be at least this much faster per frame


def speed_lines(metrics: dict[str, dict]) -> list[str]:
    sp = speed(metrics)
    sw, df = sp["surfelwarp"], sp["dynamicfusion"]
    lines = ["## Speed", "",
             f"SurfelWarp ran as {surfelwarp_variant(metrics['surfelwarp'])}.", "",
             f"**Speed ratio: SurfelWarp is {sp['ratio']:.2f}x faster per frame than DynamicFusion** "
             f"(median time per frame after the first: SurfelWarp {sw['total']:.0f} ms, "
             f"DynamicFusion {df['total']:.0f} ms; target at least {SPEED_TARGET:g}x).", "",
             "| median ms per frame | SurfelWarp | DynamicFusion |", "|---|---:|---:|",
             f"| input (read, preprocess) | {sw['input']:.0f} | {df['input']:.0f} |",
             f"| tracking (solver maps, rigid ICP, data points, non-rigid GN) | {sw['tracker']:.0f} | {df['tracker']:.0f} |",
             f"| model update (all other stages) | {sw['model']:.0f} | {df['model']:.0f} |",
             f"| total | {sw['total']:.0f} | {df['total']:.0f} |", ""]
    if sp["ratio"] < SPEED_TARGET:
        lines += [f"Below {SPEED_TARGET:g}x: SurfelWarp's frame is mostly input and tracking, which both methods "
                  f"share ({sw['input'] + sw['tracker']:.0f} of {sw['total']:.0f} ms), so even a free model update "
                  f"would make it at most {sp['ratio_bound']:.2f}x faster than DynamicFusion here; DynamicFusion's "
                  f"volumetric stages add {df['model']:.0f} ms.", ""]
    return lines


def topology_lines(phases: dict[str, list[int]], averages: dict[str, dict[str, dict]]) -> list[str]:
    contact = phases["in contact"]
    after = phases["after separation"]
    lines = ["## Topology change", "",
             f"In the ground truth the moving parts touch (gap under {CONTACT_MM:g} mm) in frames "
             f"{contact[0]}-{contact[-1]} and are apart again in frames {after[0]}-{after[-1]}. "
             "Averages over the evaluated (saved) frames of each phase:", ""]
    names = [p for p in phases if phases[p]]
    lines += ["| | " + " | ".join(f"{p}: {LABELS[n]}" for p in names for n in METHODS) + " |",
              "|---|" + "---:|" * (len(names) * len(METHODS)),
              "| evaluated frames | " + " | ".join(
                  ",".join(str(f) for f in averages[p][n]["frames"]) or "-" for p in names for n in METHODS) + " |"]
    for key, label, digits in PHASE_KEYS:
        lines.append(f"| {label} | " + " | ".join(_fmt(averages[p][n][key], digits) for p in names for n in METHODS) + " |")
    sw, df = averages["after separation"]["surfelwarp"], averages["after separation"]["dynamicfusion"]
    if df["accuracy_mean_mm"] is not None and sw["accuracy_mean_mm"] is not None:
        lines += ["", f"After separation: DynamicFusion's live surface lies {_fmt(df['accuracy_mean_mm'], 2)} mm from "
                      f"the true one on average ({_fmt(df['precision_5mm_pct'])} % of it within 5 mm), SurfelWarp's "
                      f"{_fmt(sw['accuracy_mean_mm'], 2)} mm ({_fmt(sw['precision_5mm_pct'])} %)."]
    lines += ["", "![topology change](topology.png)", ""]
    return lines


def write_report(out: Path, spec: CompareSpec, seq, metrics: dict[str, dict], results: dict[str, dict] | None,
                 normal_images: list[tuple[int, str]], topology: tuple[dict, dict] | None = None) -> Path:
    intr = seq.intrinsics
    lines = ["# SurfelWarp vs DynamicFusion", "",
             f"Input `{spec.input}` ({seq.layout}, {intr.width}x{intr.height}), "
             f"{metrics['surfelwarp']['summary']['frames']} frames from frame {seq.files[0].index}. "
             "Both methods share the rigid ICP and the non-rigid Gauss-Newton tracker; each ran alone in "
             "its own process, one after the other. Outputs: `surfelwarp/`, `dynamicfusion/` (as `surfelwarp run`).", ""]
    fields_used = {n: metrics[n].get("config", {}).get("method", {}).get("warp_field") for n in METHODS}
    if all(fields_used.values()):
        describe = lambda w: (f"nodes {1000 * w['node_radius_m']:.0f} mm apart, {w['k_skin']} skinning and "  # noqa: E731
                              f"{w['graph_k']} regularisation neighbours")
        if fields_used["surfelwarp"] == fields_used["dynamicfusion"]:
            lines += [f"Warp field of both: {describe(fields_used['surfelwarp'])}.", ""]
        else:
            lines += [f"Warp field: SurfelWarp {describe(fields_used['surfelwarp'])}; DynamicFusion "
                      f"{describe(fields_used['dynamicfusion'])}.", ""]
    lines += speed_lines(metrics)
    lines += ["## Summary", "", "| | SurfelWarp | DynamicFusion |", "|---|---:|---:|"]
    lines += [f"| {r[0]} | {r[1]} | {r[2]} |" for r in summary_rows(metrics, results)]
    if results is None:
        lines += ["", "The sequence has no ground truth: no accuracy figures."]
    else:
        lines += ["", "Accuracy, completeness and EPE: averages over the saved live frames "
                      "(`surfelwarp eval`, written to each run's `eval.json`)."]
    lines.append("")
    if topology is not None:
        lines += topology_lines(*topology)
    lines += ["## Time per frame by stage", "", "![time per frame](timing.png)", "",
              "## Model size", "", "![model size](model_size.png)", "",
              "## Memory", "", "![memory](memory.png)", ""]
    if results is not None:
        lines += ["## Accuracy against ground truth", "", "![accuracy](accuracy.png)", ""]
    if normal_images:
        lines += ["## Live models (colour = normal)", ""]
        lines += [f"Frame {frame}:\n\n![normals at frame {frame}]({name})\n" for frame, name in normal_images]
    path = out / "report.md"
    from .ply import write_atomic
    write_atomic(path, ("\n".join(lines) + "\n").encode())
    return path


def compare(spec: CompareSpec, render_frames: list[int] | None = None) -> Path:
    """Run both methods, evaluate, plot; returns the path of report.md."""
    out = Path(spec.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    seq = open_input(spec)                      # bad input fails here, before any run
    try:
        _plt()
    except ImportError:
        raise InputError(None, "compare draws its plots with matplotlib: pip install matplotlib") from None
    for name in METHODS:
        run_in_child(name, spec)
    metrics = {name: load_metrics(out / name) for name in METHODS}
    results = evaluate_runs(out, spec.input)
    plot_timing(metrics, out / "timing.png")
    plot_model_size(metrics, out / "model_size.png")
    plot_memory(metrics, out / "memory.png")
    topology = None
    if results is not None:
        plot_accuracy(results, out / "accuracy.png")
        gaps = contact_gaps(spec.input)
        phases = None if gaps is None else topology_phases(*gaps)
        if phases is not None:
            topology = (phases, phase_averages(results, phases))
            plot_topology(results, *gaps, phases, out / "topology.png")
            if render_frames is None:
                render_frames = phase_render_frames(out, phases)
    images = []
    for frame in (pick_frames(out) if render_frames is None else render_frames):
        panels = []
        observed = input_normals(seq, frame, spec.preprocess)
        if observed is not None:
            panels.append(("input depth", observed))
        for name in METHODS:
            ply = out / name / "live" / f"frame-{frame:06d}.ply"
            if ply.exists():
                panels.append((LABELS[name], render_live_normals(ply, seq.intrinsics)))
        if len(panels) > (observed is not None):
            file = f"normals-{frame:06d}.png"
            plot_normals(panels, f"frame {frame}", out / file)
            images.append((frame, file))
    return write_report(out, spec, seq, metrics, results, images, topology)


# ---------------------------------------------------------------- command line

def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _frame_list(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frame numbers separated by commas, got {text!r}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="sequence folder (any layout of CONTRACT.md)")
    p.add_argument("--out", type=Path, required=True, help="output folder (surfelwarp/, dynamicfusion/, report.md)")
    p.add_argument("--save-every", type=_positive_int, default=10, metavar="K",
                   help="write live/frame-%%06d.ply every K processed frames (and the last)")
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="override the intrinsics file")
    p.add_argument("--depth-scale", type=float, default=1000.0, help="PNG units per metre (default 1000)")
    p.add_argument("--clip-near", type=float, default=None, metavar="M", help="near clip, metres (default 0.1)")
    p.add_argument("--clip-far", type=float, default=None, metavar="M", help="far clip, metres (default 3.0)")
    p.add_argument("--start", type=int, default=0, metavar="FRAME", help="first frame index to process")
    p.add_argument("--max-frames", type=_positive_int, default=None, metavar="N")
    p.add_argument("--voxel-size", type=float, default=None, metavar="M",
                   help="DynamicFusion voxel size, metres (default 0.004)")
    p.add_argument("--no-fusion", action="store_true",
                   help="SurfelWarp as template tracking (the first frame's surfels, never fused)")
    p.add_argument("--graph-k", type=_positive_int, default=None, metavar="K",
                   help="both methods: regularise each node with its K nearest nodes (default 8); with "
                        "separate parts (fingers) K nearest may link across the gap between them")
    p.add_argument("--hierarchical", action="store_true",
                   help="DynamicFusion regularises through its hierarchical deformation tree")
    p.add_argument("--render-frames", type=_frame_list, default=None, metavar="F1,F2,..",
                   help="frames whose live models are rendered as normal maps (default: up to 3 saved ones)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars even on a terminal")


def spec_from_args(args: argparse.Namespace) -> CompareSpec:
    from .dynamicfusion import DynamicFusionParams
    from .sequence import parse_intrinsics_flag

    params = PreprocessParams()
    if args.clip_near is not None:
        params = replace(params, clip_near_m=args.clip_near)
    if args.clip_far is not None:
        params = replace(params, clip_far_m=args.clip_far)
    if not 0 <= params.clip_near_m < params.clip_far_m:
        raise InputError(None, f"--clip-near {params.clip_near_m} must be >= 0 and below --clip-far {params.clip_far_m}")
    df = DynamicFusionParams()
    if args.hierarchical:
        df = replace(df, tracking=replace(df.tracking, hierarchy=replace(df.tracking.hierarchy, enabled=True)))
    if args.voxel_size is not None:
        if not args.voxel_size > 0:
            raise InputError(None, f"--voxel-size must be positive, got {args.voxel_size}")
        # The truncation band keeps its width in voxels (3, as the defaults 12 mm / 4 mm).
        df = replace(df, tsdf=replace(df.tsdf, voxel_size_m=args.voxel_size, truncation_m=3 * args.voxel_size))
    sw_field = None
    if args.graph_k is not None:
        df = replace(df, warp_field=replace(df.warp_field, graph_k=args.graph_k))
        sw_field = df.warp_field
    return CompareSpec(input=args.input, out=args.out,
                       intrinsics=parse_intrinsics_flag(args.intrinsics) if args.intrinsics else None,
                       depth_scale=args.depth_scale, start=args.start, max_frames=args.max_frames,
                       save_every=args.save_every, preprocess=params, dynamicfusion=df, surfelwarp_warp_field=sw_field,
                       surfelwarp_fusion=not args.no_fusion,
                       progress=False if args.no_progress else None)


def run(args: argparse.Namespace) -> int:
    report = compare(spec_from_args(args), args.render_frames)
    print(f"comparison written to {report}")
    return 0
