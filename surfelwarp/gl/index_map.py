"""The fusion index map (SurfelWarp Sec. VI-A): surfels drawn as unsized points on a supersampled grid.

Each surfel lands on at most one pixel (the one whose centre is nearest its projection); where
several land on the same pixel the closest to the camera wins. Pixels store only the surfel
index: a surfel's position, normal and confidence are gathers from the arrays that were drawn,
which travel with the map. At 4x supersampling on llvmpipe, clearing and reading back two
RGBA32F attribute maps (2560x1920) cost more than drawing the points.
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
    """The index map (H*s, W*s), int32, row 0 the top image row, -1 where empty, and the
    surfels it indexes: camera-frame points and normals (N, 3) float32, confidences (N,)."""
    index: np.ndarray
    supersample: int
    intrinsics: Intrinsics       # of the supersampled grid
    points: np.ndarray
    normals: np.ndarray
    confidences: np.ndarray | None = None

    def _per_pixel(self, values: np.ndarray) -> np.ndarray:
        hit = self.index >= 0
        out = np.zeros(self.index.shape + values.shape[1:], values.dtype)
        out[hit] = values[self.index[hit]]
        return out

    @property
    def vertex(self) -> np.ndarray:
        """(H*s, W*s, 3) camera-frame position per pixel, zeros where empty."""
        return self._per_pixel(self.points)

    @property
    def normal(self) -> np.ndarray:
        return self._per_pixel(self.normals)

    @property
    def confidence(self) -> np.ndarray | None:
        return None if self.confidences is None else self._per_pixel(self.confidences)


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
    """Framebuffer of one size: index (R32I) and a depth buffer."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        size = (width, height)
        self.index = ctx.renderbuffer(size, components=1, dtype="i4")
        self.depth = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer([self.index], self.depth)


class _Renderer:
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.program = load_program(ctx, vertex="index_map.vert.glsl", fragment="index_map.frag.glsl")
        self.positions = GrowingBuffer(ctx)
        self.vao: moderngl.VertexArray | None = None
        self.vao_generation = None
        self.targets: dict[tuple[int, int], _Targets] = {}

    def _vertex_array(self) -> moderngl.VertexArray:
        if self.vao is None or self.positions.generation != self.vao_generation:
            if self.vao is not None:
                self.vao.release()
            self.vao = self.ctx.vertex_array(self.program, [(self.positions.buffer, "3f", "in_position")])
            self.vao_generation = self.positions.generation
        return self.vao

    def render(self, positions: np.ndarray, intr: Intrinsics, near: float, far: float) -> np.ndarray:
        width, height = intr.width, intr.height
        self.positions.upload(positions)
        if (width, height) not in self.targets:
            self.targets[(width, height)] = _Targets(self.ctx, width, height)
        fbo = self.targets[(width, height)].fbo
        ctx = self.ctx
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        # moderngl clears with float values; 0.0 has the all-zero bit pattern, which is why the
        # index attachment stores index + 1.
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable_only(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        ctx.point_size = 1.0
        prog = self.program
        prog["u_K"].value = (intr.fx, intr.fy, intr.cx, intr.cy)
        prog["u_size"].value = (float(width), float(height))
        prog["u_near_far"].value = (near, far)
        if len(positions):
            self._vertex_array().render(moderngl.POINTS, vertices=len(positions))
        index = read_attachment(fbo, 0, 1, "i4", height, width)
        index -= 1
        return index


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
    index = _renderer().render(positions, intr, near_m, far_m)
    return FusionMaps(index=index, supersample=int(supersample), intrinsics=intr, points=positions,
                      normals=normals, confidences=None if confidence is None else conf)
