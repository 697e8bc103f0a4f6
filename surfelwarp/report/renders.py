"""Normal-map renders of the live models and of the input depth (colour = normal)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.ply import read_ply
from surfelwarp.preprocess import PreprocessParams, preprocess
from surfelwarp.render.views import live_view, normal_colours
from surfelwarp.report.runner import METHODS

__all__ = ["normal_colours", "render_live", "input_normals", "pick_frames", "crop_to_content"]


def render_live(ply_path: Path, intrinsics: Intrinsics, colour: bool = False) -> np.ndarray:
    """render.views.live_view of a live PLY file: a mesh through mesh maps, surfels as disks of
    their radius (a point cloud without radii gets pixel-footprint disks)."""
    return live_view(*read_ply(ply_path), intrinsics, colour)


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


def crop_to_content(panels: list[tuple[str, np.ndarray]], margin_px: int = 12) -> list[tuple[str, np.ndarray]]:
    """The panels cut to the box (plus a margin) holding every panel's non-white pixels."""
    drawn = np.any([np.any(image < 1.0, axis=-1) for _, image in panels], axis=0)
    if not drawn.any():
        return panels
    rows, cols = np.flatnonzero(drawn.any(1)), np.flatnonzero(drawn.any(0))
    r0, r1 = max(rows[0] - margin_px, 0), rows[-1] + margin_px + 1
    c0, c1 = max(cols[0] - margin_px, 0), cols[-1] + margin_px + 1
    return [(label, image[r0:r1, c0:c1]) for label, image in panels]
