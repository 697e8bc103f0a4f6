"""Loads GLSL programs from the `shaders/` folder shipped as package data."""
from __future__ import annotations

from functools import lru_cache
from importlib import resources

import moderngl


@lru_cache(maxsize=None)
def shader_source(name: str) -> str:
    return resources.files("surfelwarp.shaders").joinpath(name).read_text()


_programs: dict[tuple, moderngl.Program | moderngl.ComputeShader] = {}


def load_program(ctx: moderngl.Context, vertex: str, fragment: str | None = None,
                 geometry: str | None = None, varyings: tuple[str, ...] = ()) -> moderngl.Program:
    """Compile (once per context) the program made of the named shader files."""
    key = (id(ctx), vertex, fragment, geometry, varyings)
    if key not in _programs:
        _programs[key] = ctx.program(
            vertex_shader=shader_source(vertex),
            fragment_shader=shader_source(fragment) if fragment else None,
            geometry_shader=shader_source(geometry) if geometry else None,
            varyings=varyings)
    return _programs[key]


def load_compute(ctx: moderngl.Context, name: str) -> moderngl.ComputeShader:
    """Compile (once per context) the compute shader of the named file."""
    key = (id(ctx), name)
    if key not in _programs:
        _programs[key] = ctx.compute_shader(shader_source(name))
    return _programs[key]
