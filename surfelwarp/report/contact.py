"""Where two parts touch and part (ground truth of the synthetic scenes) and each phase's errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelwarp.report.renders import pick_frames
from surfelwarp.report.runner import METHODS


CONTACT_MM = 1.0   # moving parts closer than this (ground truth) touch


def contact_gaps(seq_dir: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(frames, gap_mm): per frame the smallest surface distance between two different moving
    parts of a synthetic sequence's ground truth; None without ground truth or with fewer than
    two moving parts."""
    path = Path(seq_dir) / "groundtruth.npz"
    if not path.exists():
        return None
    from surfelwarp.data_tools.geometry import TriangleMesh
    from surfelwarp.data_tools.synth import load_groundtruth
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
