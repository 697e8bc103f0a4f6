"""Pictures of a model from a camera: normal maps of surfels or a mesh, depth in false colour,
and the panel a run saves for every saved frame (OUT/render/frame-%06d.png)."""
from __future__ import annotations

import cv2
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.mesh_maps import render_mesh_maps
from surfelwarp.render.solver_maps import render_solver_maps


def normal_colours(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1]: the usual normal-map colouring in a y-up, z-toward-viewer
    frame (a normal facing the camera is light blue); white where mask is False."""
    n = normals * np.array([1.0, -1.0, -1.0], np.float32)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return np.where(mask[..., None], 0.5 + 0.5 * n, 1.0)


def live_view(table: np.ndarray, faces: np.ndarray | None, intrinsics: Intrinsics,
              colour: bool = False) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] of a PLY vertex table (camera frame) seen from that camera:
    a mesh through mesh maps, surfels as disks of their radius (points without radii get
    pixel-footprint disks); the normal map, or with `colour` the fused red green blue where the
    table has them. White where nothing is drawn."""
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


def depth_colours(depth_m: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB: depth through the turbo colour map between its 2nd and 98th
    percentile (near red, far blue), black where there is none."""
    valid = depth_m > 0
    if not valid.any():
        return np.zeros(depth_m.shape + (3,), np.uint8)
    near, far = np.percentile(depth_m[valid], [2, 98])
    scaled = np.clip((far - depth_m) / max(far - near, 1e-6), 0, 1)
    bgr = cv2.applyColorMap(np.rint(scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    return np.where(valid[..., None], bgr[..., ::-1], 0).astype(np.uint8)


def frame_panel(live_rgb: np.ndarray, depth_m: np.ndarray, color: np.ndarray | None) -> np.ndarray:
    """The saved frame's picture, (H, 2W or 3W, 3) uint8 RGB: the live model's normal map, the
    input depth, and the colour frame where there is one, side by side."""
    parts = [np.rint(np.clip(live_rgb, 0, 1) * 255).astype(np.uint8), depth_colours(depth_m)]
    if color is not None:
        parts.append(np.asarray(color, np.uint8))
    return np.concatenate(parts, axis=1)
