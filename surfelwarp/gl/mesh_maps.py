"""Solver maps of a triangle mesh (the DynamicFusion baseline's model-to-frame data association).

Triangles are rasterised with a depth test at depth resolution. Each covered pixel holds the
point where its centre ray meets the nearest triangle (perspective-correct interpolation of the
camera-frame corners), the interpolated vertex normal, and as index the id of that triangle's
corner nearest in 3D to the point, so per-vertex data (e.g. skinning) can be looked up.
"""
from __future__ import annotations

import moderngl
import numpy as np

from ..camera import Intrinsics
from .context import gl_context
from .index_map import FAR_M, NEAR_M, GrowingBuffer, read_attachment
from .shaders import load_program
from .solver_maps import SolverMaps


class _Targets:
    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        size = (width, height)
        self.attachments = [ctx.renderbuffer(size, components=1, dtype="i4"),
                            ctx.renderbuffer(size, components=4, dtype="f4"),
                            ctx.renderbuffer(size, components=4, dtype="f4")]
        self.depth = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer(self.attachments, self.depth)


class _Renderer:
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.program = load_program(ctx, vertex="mesh_maps.vert.glsl", fragment="mesh_maps.frag.glsl",
                                    geometry="mesh_maps.geom.glsl")
        self.buffers = {name: GrowingBuffer(ctx) for name in ("position", "normal", "element")}
        self.vao: moderngl.VertexArray | None = None
        self.vao_key = None
        self.targets: dict[tuple[int, int], _Targets] = {}

    def _vertex_array(self) -> moderngl.VertexArray:
        key = tuple(b.generation for b in self.buffers.values())
        if self.vao is None or key != self.vao_key:
            if self.vao is not None:
                self.vao.release()
            b = self.buffers
            self.vao = self.ctx.vertex_array(self.program, [
                (b["position"].buffer, "3f", "in_position"),
                (b["normal"].buffer, "3f", "in_normal")],
                index_buffer=b["element"].buffer, index_element_size=4)
            self.vao_key = key
        return self.vao

    def render(self, positions, normals, elements, intr: Intrinsics, near: float, far: float):
        width, height = intr.width, intr.height
        self.buffers["position"].upload(positions)
        self.buffers["normal"].upload(normals)
        self.buffers["element"].upload(elements)
        if (width, height) not in self.targets:
            self.targets[(width, height)] = _Targets(self.ctx, width, height)
        fbo = self.targets[(width, height)].fbo
        ctx = self.ctx
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)   # index attachment stores index + 1
        ctx.enable_only(moderngl.DEPTH_TEST)        # no culling: either winding is drawn
        ctx.depth_func = "<"
        prog = self.program
        prog["u_K"].value = (intr.fx, intr.fy, intr.cx, intr.cy)
        prog["u_size"].value = (float(width), float(height))
        prog["u_near_far"].value = (near, far)
        if len(elements):
            self._vertex_array().render(moderngl.TRIANGLES, vertices=len(elements))
        index = read_attachment(fbo, 0, 1, "i4", height, width)
        index -= 1
        return (index,
                read_attachment(fbo, 1, 3, "f4", height, width),
                read_attachment(fbo, 2, 3, "f4", height, width))


_renderers: dict[int, _Renderer] = {}


def _renderer() -> _Renderer:
    ctx = gl_context()
    if id(ctx) not in _renderers:
        _renderers[id(ctx)] = _Renderer(ctx)
    return _renderers[id(ctx)]


def render_mesh_maps(vertices_cam: np.ndarray, normals_cam: np.ndarray, faces: np.ndarray,
                     intrinsics: Intrinsics, near_m: float = NEAR_M, far_m: float = FAR_M) -> SolverMaps:
    """Render a camera-frame mesh ((N, 3) vertices and normals, (F, 3) faces) at `intrinsics`.

    Returns SolverMaps: index = id of the hit triangle's corner nearest to the pixel's surface
    point (-1 where no triangle), vertex = that surface point, normal = the interpolated vertex
    normal, renormalised (as given: no flipping toward the camera). Triangles are clipped at
    near_m and far_m; triangles with a non-finite corner are dropped.
    """
    if intrinsics.width <= 0 or intrinsics.height <= 0:
        raise ValueError("intrinsics need a width and height")
    vertices = np.asarray(vertices_cam, np.float32).reshape(-1, 3)
    normals = np.asarray(normals_cam, np.float32).reshape(-1, 3)
    if len(normals) != len(vertices):
        raise ValueError("vertices and normals differ in length")
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("faces index outside the vertex array")
    elements = faces.astype(np.uint32).reshape(-1)
    index, vertex, normal = _renderer().render(vertices, normals, elements, intrinsics, near_m, far_m)
    return SolverMaps(index=index, vertex=vertex, normal=normal, intrinsics=intrinsics)
