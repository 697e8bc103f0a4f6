"""The fusion index map (SurfelWarp Sec. VI-A): surfels drawn as unsized points on a supersampled grid.

Each surfel lands on at most one pixel (the one whose centre is nearest its projection); where
several land on the same pixel the closest to the camera wins. Pixels store the surfel index and
its camera-frame position, normal and (optionally) confidence.
"""
from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from ..camera import Intrinsics
from .context import gl_context
from .shaders import load_program

NEAR_M = 0.01
FAR_M = 20.0


@dataclass(frozen=True)
class FusionMaps:
    """Maps of shape (H*s, W*s[, 3]); row 0 is the top image row. Empty pixels: index -1, zeros."""
    index: np.ndarray            # int32
    vertex: np.ndarray           # float32, camera frame
    normal: np.ndarray           # float32
    supersample: int
    intrinsics: Intrinsics       # of the supersampled grid
    confidence: np.ndarray | None = None   # float32, only when confidences were given


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


class _Targets:
    """Framebuffer of one size: index (R32I), vertex and normal (RGBA32F, read back as RGB),
    confidence (R32F) and a depth buffer."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        size = (width, height)
        self.attachments = [ctx.renderbuffer(size, components=1, dtype="i4"),
                            ctx.renderbuffer(size, components=4, dtype="f4"),
                            ctx.renderbuffer(size, components=4, dtype="f4"),
                            ctx.renderbuffer(size, components=1, dtype="f4")]
        self.depth = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer(self.attachments, self.depth)


class _Renderer:
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.program = load_program(ctx, vertex="index_map.vert.glsl", fragment="index_map.frag.glsl")
        self.buffers = {name: GrowingBuffer(ctx) for name in ("position", "normal", "confidence")}
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
                (b["normal"].buffer, "3f", "in_normal"),
                (b["confidence"].buffer, "1f", "in_confidence")])
            self.vao_key = key
        return self.vao

    def render(self, positions, normals, confidence, intr: Intrinsics, near: float, far: float,
               with_confidence: bool):
        width, height = intr.width, intr.height
        n = len(positions)
        self.buffers["position"].upload(positions)
        self.buffers["normal"].upload(normals)
        self.buffers["confidence"].upload(confidence)
        if (width, height) not in self.targets:
            self.targets[(width, height)] = _Targets(self.ctx, width, height)
        fbo = self.targets[(width, height)].fbo
        ctx = self.ctx
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        # moderngl clears every attachment with float values; 0.0 has the all-zero bit pattern,
        # which is why the index attachment stores index + 1.
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable_only(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        ctx.point_size = 1.0
        prog = self.program
        prog["u_K"].value = (intr.fx, intr.fy, intr.cx, intr.cy)
        prog["u_size"].value = (float(width), float(height))
        prog["u_near_far"].value = (near, far)
        if n:
            self._vertex_array().render(moderngl.POINTS, vertices=n)
        index = read_attachment(fbo, 0, 1, "i4", height, width)
        index -= 1
        return (index,
                read_attachment(fbo, 1, 3, "f4", height, width),
                read_attachment(fbo, 2, 3, "f4", height, width),
                read_attachment(fbo, 3, 1, "f4", height, width) if with_confidence else None)


def read_attachment(fbo: moderngl.Framebuffer, attachment: int, components: int, dtype: str,
                    height: int, width: int, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """An (H, W[, C]) block of one attachment as a fresh writable array. GL's bottom row comes
    first, which is image row 0 because the shaders map image row v to GL row v."""
    out = np.empty((height, width) if components == 1 else (height, width, components), dtype)
    fbo.read_into(out, viewport=(*origin, width, height), components=components,
                  attachment=attachment, dtype=dtype)
    return out


_renderers: dict[int, _Renderer] = {}


def _renderer() -> _Renderer:
    ctx = gl_context()
    if id(ctx) not in _renderers:
        _renderers[id(ctx)] = _Renderer(ctx)
    return _renderers[id(ctx)]


def render_index_map(positions: np.ndarray, normals: np.ndarray, intrinsics: Intrinsics,
                     supersample: int = 1, confidence: np.ndarray | None = None,
                     near_m: float = NEAR_M, far_m: float = FAR_M) -> FusionMaps:
    """Render (N, 3) camera-frame surfels as points on the grid of `intrinsics.supersampled(s)`.

    Surfels with depth outside (near_m, far_m), behind the camera, or off the grid are dropped.
    """
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, not {supersample}")
    intr = intrinsics.supersampled(int(supersample))
    if intr.width <= 0 or intr.height <= 0:
        raise ValueError("intrinsics need a width and height")
    positions = np.asarray(positions, np.float32).reshape(-1, 3)
    normals = np.asarray(normals, np.float32).reshape(-1, 3)
    if len(normals) != len(positions):
        raise ValueError("positions and normals differ in length")
    conf = (np.zeros(len(positions), np.float32) if confidence is None
            else np.asarray(confidence, np.float32).reshape(-1))
    if len(conf) != len(positions):
        raise ValueError("confidence and positions differ in length")
    index, vertex, normal, conf_map = _renderer().render(positions, normals, conf, intr, near_m, far_m,
                                                         confidence is not None)
    return FusionMaps(index=index, vertex=vertex, normal=normal, supersample=int(supersample),
                      intrinsics=intr, confidence=conf_map)
