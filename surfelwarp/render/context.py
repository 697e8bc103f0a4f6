"""The one place that creates the headless OpenGL context (EGL; Mesa llvmpipe without a GPU)."""
from __future__ import annotations

import ctypes.util

import moderngl

from surfelwarp.errors import GLUnavailableError

_context: moderngl.Context | None = None


def gl_context() -> moderngl.Context:
    """The process-wide standalone EGL context, created on first use."""
    global _context
    if _context is None:
        if ctypes.util.find_library("EGL") is None:
            raise GLUnavailableError("libEGL.so.1 is missing: install the system EGL/Mesa libraries "
                                     "(apt-get install libegl1 libgl1-mesa-dri), or run `make demo` once")
        try:
            _context = moderngl.create_context(standalone=True, backend="egl", require=430)
        except Exception as exc:  # moderngl raises plain Exception for driver failures
            raise GLUnavailableError(f"cannot create a headless EGL OpenGL 4.3 context (compute shaders) ({exc}); "
                                     "check that Mesa's EGL driver (libegl-mesa0, libgl1-mesa-dri) is installed") from None
    return _context
