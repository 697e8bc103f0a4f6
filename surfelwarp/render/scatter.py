"""Index maps drawn by compute shaders that scatter each surfel onto its pixels with atomics.

On llvmpipe every point primitive costs ~200 ns of set-up on one thread, whatever it covers
(66k points into a 2560x1920 index map: 25 ms; 275k disk splats: 134 ms). A compute shader
runs the same per-surfel work as SIMD on every core: ~10x less. The maps are the nearest-wins
images the rasteriser would give, built in two passes (nearest depth key, then the lowest
index at it) in storage buffers, the all-zero clear meaning empty.
"""
from __future__ import annotations

import moderngl
import numpy as np

from surfelwarp.render.base import GrowingBuffer
from surfelwarp.render.context import gl_context
from surfelwarp.render.shaders import load_compute

GROUP = 64     # local_size_x of the compute shaders
MAX_GROUPS_X = 65535    # GL's guaranteed work-group count per dimension: more go on a 2-D grid


class Scatter:
    """One compute program, its input buffers (bound to bindings 0, 3, ...), the key and
    index buffers (bindings 1 and 2) of a map of any size, and any scratch buffers the two
    passes share (`scratch`: binding -> uints per invocation)."""

    def __init__(self, ctx: moderngl.Context, shader: str, inputs: dict[str, int],
                 scratch: dict[int, int] | None = None):
        self.ctx, self.program = ctx, load_compute(ctx, shader)
        self.inputs = {name: (GrowingBuffer(ctx), binding) for name, binding in inputs.items()}
        self.scratch = {binding: (GrowingBuffer(ctx), uints) for binding, uints in (scratch or {}).items()}
        self.keys, self.index = GrowingBuffer(ctx), GrowingBuffer(ctx)
        self._written: tuple[int, int, int] = (-1, 0, 0)    # generation, bytes from, to of the last map

    def run(self, count: int, height: int, width: int, arrays: dict[str, np.ndarray],
            rows: tuple[int, int] | None = None, **uniforms) -> np.ndarray:
        """(height, width) int32 map of surfel indices (-1 empty) after both passes over `count`
        invocations with the named input arrays and uniforms. `rows` (first, end): the rows the
        invocations can write, if known; only those are read back, and the next call clears
        only what this one wrote (a 4x fusion map is 2 x 20 MB to clear and 20 MB to read)."""
        for name, data in arrays.items():
            buffer, binding = self.inputs[name]
            buffer.upload(data).bind_to_storage_buffer(binding)
        for binding, (buffer, uints) in self.scratch.items():
            buffer.reserve(4 * uints * count).bind_to_storage_buffer(binding)
        nbytes = 4 * height * width
        first, end = (0, height) if rows is None else (max(int(rows[0]), 0), min(int(rows[1]), height))
        end = max(end, first)
        self.keys.reserve(nbytes)
        self.index.reserve(nbytes)
        generation, dirty_from, dirty_to = self._written
        if generation != self.keys.generation + self.index.generation:
            dirty_from, dirty_to = 0, max(self.keys.buffer.size, self.index.buffer.size)
        for binding, buffer in ((1, self.keys), (2, self.index)):
            size = min(dirty_to, buffer.buffer.size) - dirty_from
            if size > 0:
                buffer.buffer.clear(size=size, offset=dirty_from)
            buffer.buffer.bind_to_storage_buffer(binding)
        self._written = (self.keys.generation + self.index.generation, 4 * first * width, 4 * end * width)
        for name, value in uniforms.items():
            self.program[name].value = value
        # Stored as ~index (0: empty): ~0 wraps to -1 in int32. Only the rows outside the band
        # are filled here (the band is read over: a 4x map is 20 MB).
        index = np.empty(height * width, np.int32)
        index[:first * width] = -1
        index[end * width:] = -1
        band = index[first * width:end * width]
        if count and end > first:
            groups = (count + GROUP - 1) // GROUP
            grid = (min(groups, MAX_GROUPS_X), (groups + MAX_GROUPS_X - 1) // MAX_GROUPS_X)
            for p in (0, 1):
                self.program["u_pass"].value = p
                self.program.run(*grid)
                self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
            self.index.buffer.read_into(band, size=band.nbytes, offset=4 * first * width)
            np.invert(band, out=band)
        else:
            band[:] = -1
        return index.reshape(height, width)

    _instances: dict = {}

    @classmethod
    def of(cls, shader: str, inputs: dict[str, int], scratch: dict[int, int] | None = None) -> "Scatter":
        """The scatter of this shader for the process's GL context (made on first use)."""
        ctx = gl_context()
        key = (shader, id(ctx))
        if key not in cls._instances:
            cls._instances[key] = cls(ctx, shader, inputs, scratch)
        return cls._instances[key]
