"""What every renderer shares: vertex buffers reused between calls, a vertex array rebuilt only
when a buffer was reallocated, framebuffers cached by size, and one renderer per GL context."""
from __future__ import annotations

import moderngl
import numpy as np

from surfelwarp.render.context import gl_context

NEAR_M = 0.01
FAR_M = 20.0


class GrowingBuffer:
    """A GL vertex buffer reused between calls; reallocated (with headroom) only when too small."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.buffer: moderngl.Buffer | None = None
        self.generation = 0   # bumps on reallocation, so users know to rebuild their VAOs

    def upload(self, data: np.ndarray) -> moderngl.Buffer:
        data = np.ascontiguousarray(data)
        if self.buffer is None or self.buffer.size < data.nbytes:
            if self.buffer is not None:
                self.buffer.release()
            self.buffer = self.ctx.buffer(reserve=max(int(data.nbytes * 1.25), 64))
            self.generation += 1
        if data.nbytes:
            self.buffer.write(data)
        return self.buffer

    def reserve(self, nbytes: int) -> moderngl.Buffer:
        """The buffer, at least nbytes long (contents undefined after a reallocation)."""
        if self.buffer is None or self.buffer.size < nbytes:
            if self.buffer is not None:
                self.buffer.release()
            self.buffer = self.ctx.buffer(reserve=max(int(nbytes), 64))
            self.generation += 1
        return self.buffer


def read_attachment(fbo: moderngl.Framebuffer, attachment: int, components: int, dtype: str,
                    height: int, width: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """An (H, W[, C]) block of one attachment as a fresh writable array. GL's bottom row comes
    first, which is image row 0 because the shaders map image row v to GL row v."""
    out = np.empty((height, width) if components == 1 else (height, width, components), dtype)
    fbo.read_into(out, viewport=(*origin, width, height), components=components,
                  attachment=attachment, dtype=dtype)
    return out


def camera_points(intrinsics, positions, normals) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 camera-frame points and normals to draw at `intrinsics`; ValueError for an
    image without a size or arrays of different lengths."""
    if intrinsics.width <= 0 or intrinsics.height <= 0:
        raise ValueError("intrinsics need a width and height")
    positions = np.asarray(positions, np.float32).reshape(-1, 3)
    normals = np.asarray(normals, np.float32).reshape(-1, 3)
    if len(normals) != len(positions):
        raise ValueError("positions and normals differ in length")
    return positions, normals


class Renderer:
    """A program drawing from named vertex buffers into framebuffers of `attachments` (a list of
    (components, dtype) renderbuffers) and a depth buffer. Subclasses set the program, the
    buffers' vertex attributes ((buffer name, format, attribute); an "element" buffer, if named
    in `buffers`, is the index buffer) and draw in `render`."""

    attachments: list[tuple[int, str]] = [(1, "i4")]
    attributes: list[tuple[str, str, str]] = []
    buffers: tuple[str, ...] = ()

    def __init__(self, ctx: moderngl.Context, program: moderngl.Program):
        self.ctx, self.program = ctx, program
        self.data = {name: GrowingBuffer(ctx) for name in self.buffers}
        self._vao: moderngl.VertexArray | None = None
        self._vao_key = None
        self._framebuffers: dict[tuple[int, int], moderngl.Framebuffer] = {}

    def vertex_array(self) -> moderngl.VertexArray:
        key = tuple(b.generation for b in self.data.values())
        if self._vao is None or key != self._vao_key:
            if self._vao is not None:
                self._vao.release()
            content = [(self.data[name].buffer, fmt, attr) for name, fmt, attr in self.attributes]
            element = self.data.get("element")
            self._vao = self.ctx.vertex_array(self.program, content,
                                              index_buffer=element.buffer if element else None,
                                              index_element_size=4)
            self._vao_key = key
        return self._vao

    def framebuffer(self, size: tuple[int, int]) -> moderngl.Framebuffer:
        """The framebuffer of this size, bound, its viewport the whole of it, cleared (colour 0:
        the all-zero bit pattern, so index attachments store index + 1; depth 1)."""
        if size not in self._framebuffers:
            colour = [self.ctx.renderbuffer(size, components=c, dtype=d) for c, d in self.attachments]
            self._framebuffers[size] = self.ctx.framebuffer(colour, self.ctx.depth_renderbuffer(size))
        fbo = self._framebuffers[size]
        fbo.use()
        fbo.viewport = (0, 0, *size)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        return fbo

    def begin(self, size: tuple[int, int], flags: int, intr, near: float, far: float) -> moderngl.Framebuffer:
        """The framebuffer of this size cleared and bound, the depth test on (plus `flags`), and
        the camera uniforms every program here has set: u_K (pinhole) and u_near_far (clip)."""
        fbo = self.framebuffer(size)
        self.ctx.enable_only(moderngl.DEPTH_TEST | flags)
        self.ctx.depth_func = "<"
        self.program["u_K"].value = (intr.fx, intr.fy, intr.cx, intr.cy)
        self.program["u_near_far"].value = (near, far)
        return fbo

    @staticmethod
    def read_index(fbo: moderngl.Framebuffer, height: int, width: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
        """Attachment 0 as surfel / vertex indices, -1 where nothing was drawn."""
        index = read_attachment(fbo, 0, 1, "i4", height, width, origin)
        index -= 1
        return index

    @classmethod
    def current(cls):
        """The renderer of this class for the process's GL context (made on first use)."""
        ctx = gl_context()
        key = (cls, id(ctx))
        if key not in _RENDERERS:
            _RENDERERS[key] = cls(ctx)
        return _RENDERERS[key]


_RENDERERS: dict[tuple[type, int], Renderer] = {}
