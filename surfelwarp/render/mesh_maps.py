"""Solver maps of a triangle mesh (the DynamicFusion baseline's model-to-frame data association).

Triangles are rasterised with a depth test at depth resolution. Each covered pixel holds the
point where its centre ray meets the nearest triangle (perspective-correct interpolation of the
camera-frame corners), the interpolated vertex normal, and as index the id of that triangle's
corner nearest in 3D to the point, so per-vertex data (e.g. skinning) can be looked up.
"""
from __future__ import annotations

import moderngl
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.base import FAR_M, NEAR_M, Renderer, camera_points, read_attachment
from surfelwarp.render.shaders import load_program
from surfelwarp.render.solver_maps import SolverMaps


class _MeshRenderer(Renderer):
    attachments = [(1, "i4"), (4, "f4"), (4, "f4")]
    attributes = [("position", "3f", "in_position"), ("normal", "3f", "in_normal")]
    buffers = ("position", "normal", "element")

    def __init__(self, ctx: moderngl.Context):
        super().__init__(ctx, load_program(ctx, vertex="mesh_maps.vert.glsl", fragment="mesh_maps.frag.glsl",
                                           geometry="mesh_maps.geom.glsl"))

    def render(self, positions, normals, elements, intr: Intrinsics, near: float, far: float):
        width, height = intr.width, intr.height
        self.data["position"].upload(positions)
        self.data["normal"].upload(normals)
        self.data["element"].upload(elements)
        fbo = self.begin((width, height), 0, intr, near, far)   # no culling: either winding is drawn
        self.program["u_size"].value = (float(width), float(height))
        if len(elements):
            self.vertex_array().render(moderngl.TRIANGLES, vertices=len(elements))
        return (self.read_index(fbo, height, width),
                read_attachment(fbo, 1, 3, "f4", height, width),
                read_attachment(fbo, 2, 3, "f4", height, width))


def render_mesh_maps(vertices_cam: np.ndarray, normals_cam: np.ndarray, faces: np.ndarray,
                     intrinsics: Intrinsics, near_m: float = NEAR_M, far_m: float = FAR_M) -> SolverMaps:
    """Render a camera-frame mesh ((N, 3) vertices and normals, (F, 3) faces) at `intrinsics`.

    Returns SolverMaps: index = id of the hit triangle's corner nearest to the pixel's surface
    point (-1 where no triangle), vertex = that surface point, normal = the interpolated vertex
    normal, renormalised (as given: no flipping toward the camera). Triangles are clipped at
    near_m and far_m; triangles with a non-finite corner are dropped.
    """
    vertices, normals = camera_points(intrinsics, vertices_cam, normals_cam)
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("faces index outside the vertex array")
    elements = faces.astype(np.uint32).reshape(-1)
    index, vertex, normal = _MeshRenderer.current().render(vertices, normals, elements, intrinsics, near_m, far_m)
    return SolverMaps(index=index, vertex=vertex, normal=normal, intrinsics=intrinsics)
