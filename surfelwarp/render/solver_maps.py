"""Solver maps (SurfelWarp Sec. VII): surfels rendered as opaque disk splats at depth resolution.

Each pixel holds the index, camera-frame position and normal of the surfel whose disk the pixel's
ray meets first; the depth test uses the ray/disk intersection depth, so overlapping splats
resolve per pixel. Only the index is drawn: position and normal are the surfel's own, gathered
from the arrays that were drawn (on llvmpipe two RGBA32F attachments cost ~15 % of the draw).
"""
from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.base import FAR_M, NEAR_M, Renderer, camera_points
from surfelwarp.render.shaders import load_program

MARGIN_PX = 32        # disks whose sprite centre falls this far off the image still draw
MIN_COS = 0.05        # grazing-ray clamp of |cos(ray, normal)| (about 87 degrees)


@dataclass(frozen=True)
class SolverMaps:
    """(H, W[, 3]) maps, row 0 = top image row. Empty pixels: index -1, zero vectors."""
    index: np.ndarray        # int32, index into the full surfel array
    vertex: np.ndarray       # float32, surfel centre, camera frame
    normal: np.ndarray       # float32, surfel normal
    intrinsics: Intrinsics


class _SplatRenderer(Renderer):
    attachments = [(1, "i4")]
    attributes = [("position", "3f", "in_position"), ("normal", "3f", "in_normal"), ("radius", "1f", "in_radius")]
    buffers = ("position", "normal", "radius", "element")

    def __init__(self, ctx: moderngl.Context):
        super().__init__(ctx, load_program(ctx, vertex="surfel_splat.vert.glsl", fragment="surfel_splat.frag.glsl"))
        self.max_point_size = float(ctx.info["GL_POINT_SIZE_RANGE"][1])

    def render(self, positions, normals, radii, elements, fill_elements, intr: Intrinsics, near: float, far: float):
        width, height = intr.width, intr.height
        fb_size = (width + 2 * MARGIN_PX, height + 2 * MARGIN_PX)
        self.data["position"].upload(positions)
        self.data["normal"].upload(normals)
        self.data["radius"].upload(radii)
        self.data["element"].upload(np.concatenate([elements, fill_elements]))
        fbo = self.begin(fb_size, moderngl.PROGRAM_POINT_SIZE, intr, near, far)
        prog = self.program
        prog["u_fb_size"].value = (float(fb_size[0]), float(fb_size[1]))
        prog["u_margin"].value = float(MARGIN_PX)
        prog["u_max_size"].value = self.max_point_size
        prog["u_min_cos"].value = MIN_COS
        # The fill surfels draw behind every depth of the first set: they show only where it left
        # the pixel empty.
        first_scale = 0.5 if len(fill_elements) else 1.0
        for first, count, layer in ((0, len(elements), (0.0, first_scale)),
                                    (len(elements), len(fill_elements), (0.5, 0.5))):
            if count:
                prog["u_depth_layer"].value = layer
                self.vertex_array().render(moderngl.POINTS, vertices=count, first=first)
        return self.read_index(fbo, height, width, (MARGIN_PX, MARGIN_PX))


def _elements(indices: np.ndarray, n: int) -> np.ndarray:
    elements = np.asarray(indices).reshape(-1)
    if elements.dtype == bool:
        raise ValueError("indices must be integer indices, not a mask")
    if len(elements) and (elements.min() < 0 or elements.max() >= n):
        raise ValueError("indices out of range")
    return elements.astype(np.uint32)


def render_solver_maps(positions: np.ndarray, normals: np.ndarray, radii: np.ndarray,
                       intrinsics: Intrinsics, indices: np.ndarray | None = None,
                       near_m: float = NEAR_M, far_m: float = FAR_M,
                       fill_indices: np.ndarray | None = None) -> SolverMaps:
    """Render (N, 3) camera-frame surfels (normals, (N,) radii in metres) as opaque disks.

    `indices` selects the surfels drawn (e.g. the stable ones); maps still hold full-array indices.
    `fill_indices` are drawn only on the pixels the first set leaves empty.
    Disks reaching outside (near_m, far_m) in depth are dropped; a disk whose projection is wider
    than the driver's largest point size (255 px on llvmpipe) is cut to that square.
    """
    positions, normals = camera_points(intrinsics, positions, normals)
    radii = np.asarray(radii, np.float32).reshape(-1)
    n = len(positions)
    if len(radii) != n:
        raise ValueError("positions and radii differ in length")
    elements = np.arange(n, dtype=np.uint32) if indices is None else _elements(indices, n)
    fill = np.zeros(0, np.uint32) if fill_indices is None else _elements(fill_indices, n)
    index = _SplatRenderer.current().render(positions, normals, radii, elements, fill, intrinsics, near_m, far_m)
    hit = index >= 0
    drawn = index[hit]
    vertex = np.zeros(index.shape + (3,), np.float32)
    normal = np.zeros(index.shape + (3,), np.float32)
    vertex[hit], normal[hit] = positions[drawn], normals[drawn]
    return SolverMaps(index=index, vertex=vertex, normal=normal, intrinsics=intrinsics)


def maps_to_world(maps: SolverMaps, T_camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solver maps in world coordinates, zero where no surfel was drawn (as rigid ICP expects)."""
    hit = maps.index >= 0
    R = T_camera_to_world[:3, :3].astype(np.float32)
    vertex, normal = np.zeros_like(maps.vertex), np.zeros_like(maps.normal)
    vertex[hit] = maps.vertex[hit] @ R.T + T_camera_to_world[:3, 3].astype(np.float32)
    normal[hit] = maps.normal[hit] @ R.T
    return vertex, normal
