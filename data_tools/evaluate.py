"""`surfelwarp eval OUT SEQ`: scores a run (CONTRACT.md outputs) against ground truth.

With a synthetic sequence (SEQ/groundtruth.npz, see data_tools.synth), for every saved
OUT/live/frame-%06d.ply:
- accuracy: median (and mean) exact point-to-triangle distance of the live points to the
  ground-truth mesh of that frame, mm (the whole mesh: live points may show parts not visible
  in this frame);
- precision / completeness / F-score at 5 mm and 1 cm, %: precision = share of live points
  within the threshold of the GT mesh; completeness = share of the GT surface visible in that
  frame (clean GT depth rendered and back-projected, every `stride`-th pixel) with a live
  point within the threshold; F = 2PC / (P + C);
- normal consistency: mean |n_live . n_gt| with n_gt the interpolated GT normal at the
  closest GT point;
- far_2cm_pct: share of live points more than 2 cm from the GT mesh (a model that left the
  surface), %;
- depth_explained_1cm_pct: share of the frame's valid input depth pixels (the run's clipping
  and border crop, every `stride`-th pixel) with a live point within 1 cm, %;
- end-point error (EPE), mm: each live point's ref_* position is snapped to the GT mesh of
  its reference_frame (closest point: triangle + barycentric coordinates), the same
  barycentric point on this frame's GT mesh is its true position; EPE = |live - true|
  (mean, median, % under 1 and 2 cm; also mean and median over the points on moving parts,
  i.e. whose snapped triangle has a vertex marked `moving`). Not computed (null) where
  reference_frame is the frame itself: such a run claims no correspondence over time;
- for scale, the EPE of standing still (zero_motion_epe_mm): how far the surface each live
  point shows has truly moved since the run's first frame, i.e. what a method that does not
  track at all (the observe method) would score.
With DeepDeform-style scene flow (SEQ/scene_flow/<name>_<source>_<target>.sflow): the EPE of
the target frame's live points whose ref_* position (source frame's camera, reference_frame =
source) lands on an object pixel with known flow, and, for scale, the EPE of not moving at all.
Trajectory (any ground truth with poses, also 7-Scenes-style frame-%06d.pose.txt): camera
poses of metrics.json and of the ground truth, both relative to the run's first frame; ATE =
RMSE of the translation difference without alignment, cm (also after the best rigid
alignment, the largest translation error of any frame in mm, the mean rotation error in
degrees, and the step bias: each frame's camera step's error along the true step, as a share of
it, averaged over the steps of at least 1 mm, in %: negative where the estimate lags the motion,
which ATE only shows summed).
Writes OUT/eval.json: {"run", "sequence", "ground_truth", "frames": [...], "average": {...},
"trajectory": {...}}; values that cannot be computed are null.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.errors import InputError
from surfelwarp.io.ply import read_ply, write_atomic
from surfelwarp.io.sequence import open_sequence

from . import sceneflow
from .geometry import TriangleMesh
from .meshes import vertex_normals
from .synth import GroundTruth, load_groundtruth
from .trajectory import trajectory_errors

THRESHOLDS_MM = (5, 10)
FRAME_KEYS = ("points", "accuracy_median_mm", "accuracy_mean_mm",
              *(f"{kind}_{t}mm_pct" for t in THRESHOLDS_MM for kind in ("precision", "completeness", "fscore")),
              "normal_consistency", "far_2cm_pct", "depth_explained_1cm_pct", "epe_mean_mm", "epe_median_mm", "epe_under_1cm_pct", "epe_under_2cm_pct",
              "moving_points", "epe_moving_mean_mm", "epe_moving_median_mm", "zero_motion_epe_mm")
NOT_MEANINGFUL = ("every part of the scene moves and the camera is still: the run's camera pose "
                  "carries the scene's common motion, so ATE is not a tracking error here")


def _read_metrics(run_dir: Path) -> dict:
    path = run_dir / "metrics.json"
    try:
        doc = json.loads(path.read_text())
        frames = doc["frames"]
        for f in frames:
            int(f["frame"]), np.asarray(f["camera_to_world"], dtype=float).reshape(4, 4)
    except FileNotFoundError:
        raise InputError(path, "no metrics.json: not a run output folder") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"metrics.json does not parse ({exc.__class__.__name__}: {exc})") from None
    return doc


def _live_files(run_dir: Path) -> dict[int, Path]:
    found = {}
    for path in (run_dir / "live").glob("frame-*.ply"):
        m = re.fullmatch(r"frame-(\d+)\.ply", path.name)
        if m:
            found[int(m.group(1))] = path
    return dict(sorted(found.items()))


def _read_live(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        table, _ = read_ply(path)
        names = table.dtype.names or ()
        missing = [n for n in ("x", "y", "z", "nx", "ny", "nz", "ref_x", "ref_y", "ref_z") if n not in names]
        if missing:
            raise InputError(path, f"live PLY lacks vertex properties {' '.join(missing)}")
    except InputError:
        raise
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read live PLY ({exc.__class__.__name__}: {exc})") from None

    def stack(*names):
        return np.stack([table[n].astype(np.float64) for n in names], -1)

    live, normal, ref = stack("x", "y", "z"), stack("nx", "ny", "nz"), stack("ref_x", "ref_y", "ref_z")
    # A diverged tracker can write non-finite points: they cannot be scored, so leave them out.
    finite = np.isfinite(live).all(1) & np.isfinite(ref).all(1) & np.isfinite(normal).all(1)
    if not finite.any():
        raise InputError(path, "no live point has finite coordinates (the tracker diverged)")
    return live[finite], normal[finite], ref[finite]


def _pct(mask: np.ndarray) -> float:
    return float(100.0 * np.mean(mask))


def _fscore(p: float, r: float) -> float:
    return 0.0 if p + r == 0 else 2 * p * r / (p + r)


def _depth_points(seq, frame: int, preprocess: dict, stride: int) -> np.ndarray | None:
    """The frame's valid depth pixels as camera-frame points (every stride-th pixel), with the
    run's clipping and border crop (config.preprocess); None without that frame."""
    files = {f.index: f for f in seq.files}
    if frame not in files:
        return None
    depth = seq.read_depth(files[frame]).astype(np.float32)
    near, far = preprocess.get("clip_near_m", 0.1), preprocess.get("clip_far_m", 3.0)
    depth[(depth < near) | (depth > far)] = 0
    b = int(preprocess.get("boundary_crop_px", 10))
    if b > 0:
        depth[:b], depth[-b:], depth[:, :b], depth[:, -b:] = 0, 0, 0, 0
    points = seq.intrinsics.backproject(depth)[::stride, ::stride].reshape(-1, 3)
    return points[points[:, 2] > 0]


class _SyntheticScorer:
    def __init__(self, gt: GroundTruth, stride: int, seq=None, preprocess: dict | None = None):
        from .render import MeshRenderer

        self.gt, self.stride = gt, stride
        self.seq, self.preprocess = seq, preprocess or {}
        self.renderer = MeshRenderer(gt.intrinsics)
        self._meshes: dict[int, TriangleMesh] = {}

    def mesh(self, index: int) -> TriangleMesh:
        if index not in self._meshes:
            if len(self._meshes) > 4:
                self._meshes.pop(next(iter(self._meshes)))
            self._meshes[index] = TriangleMesh(self.gt.vertices[index], self.gt.faces)
        return self._meshes[index]

    def visible_samples(self, index: int) -> np.ndarray:
        depth, _ = self.renderer.render(self.gt.vertices[index], self.gt.faces)
        points = self.gt.intrinsics.backproject(depth)[::self.stride, ::self.stride].reshape(-1, 3)
        return points[points[:, 2] > 0]

    def _carried(self, near, index: int) -> np.ndarray:
        """The closest points `near` (face + barycentric) on the GT mesh of frame `index`."""
        corners = self.gt.vertices[index].astype(np.float64)[self.gt.faces[near.face]]
        return np.einsum("ni,nij->nj", near.bary, corners)

    def score(self, frame: int, reference: int, live: np.ndarray, normals: np.ndarray, ref: np.ndarray,
              first: int | None = None) -> dict:
        out = dict.fromkeys(FRAME_KEYS)
        out["points"] = len(live)
        if len(live) == 0:
            return out
        fi, ri = self.gt.index(frame), self.gt.index(reference)
        mesh = self.mesh(fi)
        near = mesh.query(live)
        dist_mm = 1000 * near.distance
        out["accuracy_median_mm"] = float(np.median(dist_mm))
        out["accuracy_mean_mm"] = float(np.mean(dist_mm))
        out["far_2cm_pct"] = _pct(dist_mm > 20)
        depth = _depth_points(self.seq, frame, self.preprocess, self.stride) if self.seq is not None else None
        if depth is not None and len(depth):
            out["depth_explained_1cm_pct"] = _pct(KDTree(live).query(depth, k=1)[0] < 0.01)
        samples = self.visible_samples(fi)
        coverage_mm = 1000 * KDTree(live).query(samples, k=1)[0] if len(samples) else np.zeros(0)
        for t in THRESHOLDS_MM:
            p = _pct(dist_mm < t)
            c = _pct(coverage_mm < t) if len(samples) else None
            out[f"precision_{t}mm_pct"], out[f"completeness_{t}mm_pct"] = p, c
            out[f"fscore_{t}mm_pct"] = None if c is None else _fscore(p, c)
        gt_n = mesh.interpolate(vertex_normals(mesh.vertices, mesh.faces), near.face, near.bary)
        gt_n /= np.maximum(np.linalg.norm(gt_n, axis=1, keepdims=True), 1e-12)
        length = np.linalg.norm(normals, axis=1)
        ok = np.isfinite(length) & (length > 1e-6)
        if ok.any():
            out["normal_consistency"] = float(np.mean(np.abs(np.sum(normals[ok] * gt_n[ok], 1)) / length[ok]))
        if first is not None and first != frame:
            moved = self._carried(near, fi) - self._carried(near, self.gt.index(first))
            out["zero_motion_epe_mm"] = float(1000 * np.mean(np.linalg.norm(moved, axis=1)))
        if frame == reference:
            # ref_* is the live point itself: the run claims no correspondence over time (the
            # observe method, a tracker's first frame), so an EPE would be vacuously zero.
            return out
        snapped = self.mesh(ri).query(ref)
        truth = self._carried(snapped, fi)
        epe_mm = 1000 * np.linalg.norm(live - truth, axis=1)
        out["epe_mean_mm"], out["epe_median_mm"] = float(np.mean(epe_mm)), float(np.median(epe_mm))
        out["epe_under_1cm_pct"], out["epe_under_2cm_pct"] = _pct(epe_mm < 10), _pct(epe_mm < 20)
        # Points on moving parts alone: a static wall would otherwise hide the tracking error.
        moving = self.gt.moving[self.gt.faces[snapped.face]].any(axis=1)
        out["moving_points"] = int(moving.sum())
        if moving.any():
            out["epe_moving_mean_mm"] = float(np.mean(epe_mm[moving]))
            out["epe_moving_median_mm"] = float(np.median(epe_mm[moving]))
        return out

    def release(self) -> None:
        self.renderer.release()


def _pose_file_poses(seq_dir: Path, frames: list[int]) -> dict[int, np.ndarray]:
    poses = {}
    for f in frames:
        path = seq_dir / f"frame-{f:06d}.pose.txt"
        if not path.exists():
            continue
        try:
            pose = np.loadtxt(path, dtype=np.float64).reshape(4, 4)
        except (OSError, ValueError):
            raise InputError(path, "pose file does not parse: expected a 4x4 matrix") from None
        if np.isfinite(pose).all():
            poses[f] = pose
    return poses


def _average(rows: list[dict]) -> dict:
    avg = {}
    for key in FRAME_KEYS:
        values = [r[key] for r in rows if r.get(key) is not None]
        avg[key] = float(np.mean(values)) if values else None
    return avg


def evaluate(run_dir, seq_dir, stride: int = 2) -> dict:
    """Score the run in `run_dir` against the ground truth in `seq_dir`; writes run_dir/eval.json."""
    run_dir, seq_dir = Path(run_dir), Path(seq_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "run output folder does not exist")
    if not seq_dir.is_dir():
        raise InputError(seq_dir, "sequence folder does not exist")
    metrics = _read_metrics(run_dir)
    records = {int(f["frame"]): f for f in metrics["frames"]}
    estimated = {f: np.asarray(r["camera_to_world"], dtype=np.float64).reshape(4, 4) for f, r in records.items()}
    rows = []
    if (seq_dir / "groundtruth.npz").exists():
        gt = load_groundtruth(seq_dir)
        kind = "synthetic"
        truth = {int(f): gt.camera_to_world[i] for i, f in enumerate(gt.frames)}
        live = _live_files(run_dir)
        if not live:
            raise InputError(run_dir / "live", "no live/frame-%06d.ply files to evaluate")
        scorer = _SyntheticScorer(gt, stride, open_sequence(seq_dir), metrics.get("config", {}).get("preprocess"))
        try:
            for frame, path in live.items():
                if frame not in records:
                    raise InputError(path, f"frame {frame} is not listed in metrics.json")
                reference = int(records[frame].get("reference_frame", frame))
                for f in (frame, reference, min(records)):
                    if f not in truth:
                        raise InputError(seq_dir / "groundtruth.npz", f"has no frame {f} (needed by {path.name})")
                row = {"frame": frame, "reference_frame": reference}
                row.update(scorer.score(frame, reference, *_read_live(path), first=min(records)))
                rows.append(row)
        finally:
            scorer.release()
        if gt.moving.all() and np.allclose(gt.camera_to_world, gt.camera_to_world[:1]):
            truth = {}
    elif sceneflow.flow_files(seq_dir):
        kind = "sceneflow"
        truth = {}
        live = _live_files(run_dir)
        intrinsics = open_sequence(seq_dir).intrinsics
        for path, name, source, target in sceneflow.flow_files(seq_dir):
            if target not in live:
                raise InputError(run_dir / "live", f"no live/frame-{target:06d}.ply for the scene flow {path.name}")
            reference = int(records.get(target, {}).get("reference_frame", -1))
            if reference != source:
                raise InputError(live[target], f"reference_frame is {reference}, but the scene flow {path.name} "
                                               f"starts at frame {source}: run from --start {source} without fusion")
            row = {"frame": target, "reference_frame": source}
            row.update(sceneflow.sceneflow_errors(live[target], path, sceneflow.mask_for(seq_dir, name, source),
                                                  intrinsics))
            rows.append(row)
    elif list(seq_dir.glob("frame-*.pose.txt")):
        kind = "poses"
        truth = _pose_file_poses(seq_dir, list(records))
    else:
        raise InputError(seq_dir, "no ground truth: expected groundtruth.npz (from `surfelwarp synth`) "
                                  "or frame-%06d.pose.txt camera poses")
    result = {"run": str(run_dir), "sequence": str(seq_dir), "ground_truth": kind,
              "method": metrics.get("method"), "frames": rows, "average": _average(rows) if rows else {},
              "trajectory": trajectory_errors(estimated, truth)}
    if kind == "synthetic" and not truth:
        result["trajectory"]["note"] = NOT_MEANINGFUL
    write_atomic(run_dir / "eval.json", (json.dumps(result, indent=1) + "\n").encode())
    return result


def _fmt(value, digits=1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_table(result: dict) -> str:
    lines = []
    if result["frames"]:
        header = (f"{'frame':>6} {'ref':>5} {'points':>7} {'acc mm':>7} {'>2cm%':>6} {'F@5mm':>6} {'F@1cm':>6} "
                  f"{'comp@1cm':>8} {'expl%':>6} {'normal':>6} {'EPE mm':>7} {'med':>6} {'<1cm%':>6} {'<2cm%':>6} "
                  f"{'EPE mov':>7}")
        lines.append(header)

        def line(label, ref, r):
            r = {key: r.get(key) for key in FRAME_KEYS}
            return (f"{label:>6} {ref:>5} {_fmt(r['points'], 0):>7} {_fmt(r['accuracy_median_mm'], 2):>7} "
                    f"{_fmt(r['far_2cm_pct']):>6} {_fmt(r['fscore_5mm_pct']):>6} {_fmt(r['fscore_10mm_pct']):>6} "
                    f"{_fmt(r['completeness_10mm_pct']):>8} {_fmt(r['depth_explained_1cm_pct']):>6} "
                    f"{_fmt(r['normal_consistency'], 3):>6} "
                    f"{_fmt(r['epe_mean_mm']):>7} {_fmt(r['epe_median_mm']):>6} "
                    f"{_fmt(r['epe_under_1cm_pct']):>6} {_fmt(r['epe_under_2cm_pct']):>6} "
                    f"{_fmt(r['epe_moving_mean_mm']):>7}")

        for r in result["frames"]:
            lines.append(line(r["frame"], r["reference_frame"], r))
        lines.append(line("mean", "", result["average"]))
    t = result["trajectory"]
    zero = result["average"].get("zero_motion_epe_mm")
    if zero is not None:
        lines.append(f"EPE of standing still (zero motion): {zero:.1f} mm")
    if t.get("note"):
        lines.append(f"no ATE: {t['note']}")
        return "\n".join(lines)
    if result["ground_truth"] == "sceneflow":
        return "\n".join(lines)
    lines.append(f"trajectory over {t['frames']} frames: ATE {_fmt(t['ate_cm'], 2)} cm "
                 f"(aligned {_fmt(t['ate_aligned_cm'], 2)} cm), largest error {_fmt(t.get('max_translation_error_mm'), 1)} mm, "
                 f"rotation error {_fmt(t['rotation_error_deg'], 2)} deg, step bias {_fmt(t.get('step_bias_pct'), 2)} %")
    return "\n".join(lines)


def _stride(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="run output folder (metrics.json, live/)")
    parser.add_argument("seq", type=Path, help="sequence folder with groundtruth.npz or frame-%%06d.pose.txt")
    parser.add_argument("--stride", type=_stride, default=2, metavar="PX",
                        help="sample the visible GT surface every PX pixels for completeness (default 2)")


def run(args: argparse.Namespace) -> int:
    result = evaluate(args.out, args.seq, stride=args.stride)
    print(format_table(result))
    print(f"written to {Path(args.out) / 'eval.json'}")
    return 0
