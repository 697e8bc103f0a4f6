"""Renders camera-frame triangle meshes into linear depth, normal and material maps with moderngl.

Projection is the OpenCV pinhole of surfelwarp.camera (pixel (0, 0) = centre of the
top-left pixel), one sample at each pixel centre, so a planar triangle's depth is exact.
"""
from __future__ import annotations

import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.context import gl_context
from surfelwarp.render.shaders import load_program

from .meshes import vertex_normals


class MeshRenderer:
    """Depth (metres, 0 = nothing), camera-facing unit normals and the material point seen
    (the vertices' rest positions interpolated; for the texture) of a mesh, per pixel."""

    def __init__(self, intrinsics: Intrinsics, near_m: float = 0.05, far_m: float = 20.0):
        import moderngl

        self.intrinsics = intrinsics
        self.ctx = ctx = gl_context()
        self.program = load_program(ctx, vertex="synth_depth.vert.glsl", fragment="synth_depth.frag.glsl")
        size = (intrinsics.width, intrinsics.height)
        self.target = ctx.texture(size, 4, dtype="f4")
        self.material = ctx.texture(size, 4, dtype="f4")
        self.depth = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer(color_attachments=[self.target, self.material], depth_attachment=self.depth)
        self.program["intrinsics"].value = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
        self.program["size"].value = size
        self.program["clip_range"].value = (near_m, far_m)
        self._moderngl = moderngl
        self._faces_key = self._faces = None
        self._vbo = self._ibo = self._vao = None

    def _bind(self, n_vertices: int, faces: np.ndarray) -> None:
        key = (n_vertices, id(faces))
        if key == self._faces_key and self._faces is faces:
            return
        for obj in (self._vao, self._vbo, self._ibo):
            if obj is not None:
                obj.release()
        self._vbo = self.ctx.buffer(reserve=n_vertices * 36)
        self._ibo = self.ctx.buffer(np.ascontiguousarray(faces, dtype="u4").tobytes())
        self._vao = self.ctx.vertex_array(self.program, [(self._vbo, "3f 3f 3f", "in_position", "in_normal",
                                                          "in_material")],
                                          index_buffer=self._ibo, index_element_size=4)
        self._faces_key, self._faces = key, faces

    def render(self, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float32 depth and (H, W, 3) float32 normals of camera-frame `vertices`."""
        depth, normal, _ = self.render_maps(vertices, faces, vertices, normals)
        return depth, normal

    def render_maps(self, vertices: np.ndarray, faces: np.ndarray, material: np.ndarray,
                    normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth, normals and (H, W, 3) float32 material points (per-vertex `material`
        interpolated; 0 where nothing is drawn) of camera-frame `vertices`."""
        if normals is None:
            normals = vertex_normals(vertices, faces)
        self._bind(len(vertices), faces)
        self._vbo.write(np.hstack([vertices, normals, material]).astype("f4").tobytes())
        self.fbo.use()
        self.ctx.viewport = (0, 0, self.intrinsics.width, self.intrinsics.height)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(self._moderngl.DEPTH_TEST)
        self.ctx.disable(self._moderngl.CULL_FACE)
        self._vao.render(self._moderngl.TRIANGLES)
        shape = (self.intrinsics.height, self.intrinsics.width, 4)
        data = np.frombuffer(self.fbo.read(components=4, dtype="f4", attachment=0), dtype=np.float32).reshape(shape)
        mat = np.frombuffer(self.fbo.read(components=4, dtype="f4", attachment=1), dtype=np.float32).reshape(shape)
        return data[..., 0].copy(), data[..., 1:].copy(), mat[..., :3].copy()

    def release(self) -> None:
        for obj in (self._vao, self._vbo, self._ibo, self.fbo, self.target, self.material, self.depth):
            if obj is not None:
                obj.release()
        self._vao = self._vbo = self._ibo = None
        self._faces_key = None


def incidence_cosine(normals: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """|cos| of the angle between each pixel's viewing ray and its surface normal."""
    h, w = normals.shape[:2]
    u = (np.arange(w, dtype=np.float32) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(h, dtype=np.float32) - intrinsics.cy) / intrinsics.fy
    rays = np.empty((h, w, 3), np.float32)
    rays[..., 0], rays[..., 1], rays[..., 2] = u[None, :], v[:, None], 1.0
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return np.abs(np.sum(rays * normals, axis=-1))
