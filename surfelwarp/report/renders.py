"""Normal-map renders of the live models and of the input depth (colour = normal)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.io.ply import read_ply
from surfelwarp.preprocess import PreprocessParams, preprocess
from surfelwarp.report.runner import METHODS


def normal_colours(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1]: the usual normal-map colouring in a y-up, z-toward-viewer
    frame (a normal facing the camera is light blue); white where mask is False."""
    n = normals * np.array([1.0, -1.0, -1.0], np.float32)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return np.where(mask[..., None], 0.5 + 0.5 * n, 1.0)


def render_live(ply_path: Path, intrinsics: Intrinsics, colour: bool = False) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] of a live PLY from its camera: the normal map, or with
    `colour` the points' fused red green blue (white where nothing is drawn; the normal map if
    the PLY has no colour)."""
    from surfelwarp.render.mesh_maps import render_mesh_maps
    from surfelwarp.render.solver_maps import render_solver_maps

    table, faces = read_ply(ply_path)
    stack = lambda *names: np.stack([table[n] for n in names], -1).astype(np.float32)  # noqa: E731
    points, normals = stack("x", "y", "z"), stack("nx", "ny", "nz")
    if faces is not None and len(faces):
        maps = render_mesh_maps(points, normals, faces, intrinsics)
    else:
        radius = table["radius"].astype(np.float32) if "radius" in table.dtype.names \
            else np.sqrt(2.0) * points[:, 2] / intrinsics.focal_px
        maps = render_solver_maps(points, normals, radius, intrinsics)
    drawn = maps.index >= 0
    if not (colour and "red" in table.dtype.names):
        return normal_colours(maps.normal, drawn)
    rgb = stack("red", "green", "blue") / 255.0
    return np.where(drawn[..., None], rgb[np.maximum(maps.index, 0)], 1.0)


def render_live_normals(ply_path: Path, intrinsics: Intrinsics) -> np.ndarray:
    """Normal-map colours of a live PLY: a mesh with mesh maps, surfels with solver maps (disks
    of their radius; a point cloud without radii gets pixel-footprint disks)."""
    return render_live(ply_path, intrinsics)


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
