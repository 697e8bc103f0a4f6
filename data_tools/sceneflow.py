"""Tracking error against DeepDeform-style ground-truth scene flow.

`scene_flow/<name>_<source>_<target>.sflow`: uint32 width, height, channels, then float32
[C, H, W] data: the 3D motion (metres, camera frame) of every pixel of the source frame to the
target frame; -inf where unknown. `mask/<source>_<name>.png` marks the object.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from surfelwarp.errors import InputError
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.ply import read_ply

_NAME = re.compile(r"(.+)_(\d+)_(\d+)\.sflow")


def read_sflow(path: Path) -> np.ndarray:
    data = Path(path).read_bytes()
    if len(data) < 12:
        raise InputError(path, "scene flow file is truncated")
    w, h, c = np.frombuffer(data[:12], "<u4")
    if len(data) != 12 + 4 * int(w) * int(h) * int(c):
        raise InputError(path, f"scene flow file size does not match its {w}x{h}x{c} header")
    return np.frombuffer(data, "<f4", offset=12).reshape(int(c), int(h), int(w))


def flow_files(seq_dir: Path) -> list[tuple[Path, str, int, int]]:
    found = []
    for path in sorted((Path(seq_dir) / "scene_flow").glob("*.sflow")):
        m = _NAME.fullmatch(path.name)
        if m:
            found.append((path, m.group(1), int(m.group(2)), int(m.group(3))))
    return found


def sceneflow_errors(live_ply: Path, flow_path: Path, mask_path: Path | None, intrinsics: Intrinsics) -> dict:
    """EPE of live points whose reference position projects onto a source pixel with known flow.

    The true target position of such a point is its reference position plus that pixel's flow.
    """
    flow = read_sflow(flow_path)
    _, h, w = flow.shape
    vertices, _ = read_ply(live_ply)
    ref = np.stack([vertices["ref_x"], vertices["ref_y"], vertices["ref_z"]], 1).astype(np.float64)
    live = np.stack([vertices["x"], vertices["y"], vertices["z"]], 1).astype(np.float64)
    uv = np.rint(intrinsics.project(ref)).astype(np.int64)
    inside = (ref[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    uv, ref, live = uv[inside], ref[inside], live[inside]
    motion = flow[:, uv[:, 1], uv[:, 0]].T.astype(np.float64)
    keep = np.isfinite(motion).all(axis=1)
    if mask_path is not None:
        mask = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
        if mask is None:
            raise InputError(mask_path, "cannot read mask")
        keep &= mask[uv[:, 1], uv[:, 0]] > 0
    if not keep.any():
        raise InputError(live_ply, "no live point maps onto a source pixel with known scene flow")
    error = np.linalg.norm(live[keep] - (ref[keep] + motion[keep]), axis=1)
    still = np.linalg.norm(motion[keep], axis=1)
    return {"points": int(keep.sum()), "epe_mean_mm": 1000 * float(error.mean()),
            "epe_median_mm": 1000 * float(np.median(error)),
            "epe_under_1cm_pct": 100 * float(np.mean(error < 0.01)),
            "epe_under_2cm_pct": 100 * float(np.mean(error < 0.02)),
            "zero_motion_epe_mm": 1000 * float(still.mean())}


def mask_for(seq_dir: Path, name: str, source: int) -> Path | None:
    path = Path(seq_dir) / "mask" / f"{source:06d}_{name}.png"
    return path if path.exists() else None
