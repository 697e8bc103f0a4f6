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
    """One compute program, its input buffers (bound to bindings 0, 3, ...) and the key and
    index buffers (bindings 1 and 2) of a map of any size."""

    def __init__(self, ctx: moderngl.Context, shader: str, inputs: dict[str, int]):
        self.ctx, self.program = ctx, load_compute(ctx, shader)
        self.inputs = {name: (GrowingBuffer(ctx), binding) for name, binding in inputs.items()}
        self.keys, self.index = GrowingBuffer(ctx), GrowingBuffer(ctx)

    def run(self, count: int, height: int, width: int, arrays: dict[str, np.ndarray], **uniforms) -> np.ndarray:
        """(height, width) int32 map of surfel indices (-1 empty) after both passes over `count`
        invocations with the named input arrays and uniforms."""
        for name, data in arrays.items():
            buffer, binding = self.inputs[name]
            buffer.upload(data).bind_to_storage_buffer(binding)
        nbytes = 4 * height * width
        for binding, buffer in ((1, self.keys), (2, self.index)):
            buffer.reserve(nbytes).clear(size=nbytes)
            buffer.buffer.bind_to_storage_buffer(binding)
        for name, value in uniforms.items():
            self.program[name].value = value
        out = np.zeros(height * width, np.uint32)
        if count:
            groups = (count + GROUP - 1) // GROUP
            grid = (min(groups, MAX_GROUPS_X), (groups + MAX_GROUPS_X - 1) // MAX_GROUPS_X)
            for p in (0, 1):
                self.program["u_pass"].value = p
                self.program.run(*grid)
                self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
            self.index.buffer.read_into(out, size=nbytes)
        # Stored as ~index (0: empty): ~0 wraps to -1 in int32.
        index = out.view(np.int32)
        np.invert(index, out=index)
        return index.reshape(height, width)

    _instances: dict = {}

    @classmethod
    def of(cls, shader: str, inputs: dict[str, int]) -> "Scatter":
        """The scatter of this shader for the process's GL context (made on first use)."""
        ctx = gl_context()
        key = (shader, id(ctx))
        if key not in cls._instances:
            cls._instances[key] = cls(ctx, shader, inputs)
        return cls._instances[key]
