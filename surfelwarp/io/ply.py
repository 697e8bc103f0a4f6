"""Binary little-endian PLY, as CONTRACT.md lays it out, written atomically."""
from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO, Callable

import numpy as np

from surfelwarp.errors import OutputError

_PLY_TYPES = {"f4": "float", "u4": "uint", "i4": "int", "u1": "uchar", "f8": "double", "i1": "char",
              "u2": "ushort", "i2": "short"}
_NUMPY_TYPES = {v: k for k, v in _PLY_TYPES.items()} | {"float32": "f4", "uint32": "u4", "int32": "i4",
                                                          "uint8": "u1", "float64": "f8", "int8": "i1"}

VERTEX_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "ref_x", "ref_y", "ref_z")
SURFEL_FIELDS = ("radius", "confidence")
COLOR_FIELDS = ("red", "green", "blue")


def vertex_table(position, normal, ref_position, radius=None, confidence=None, ids=None, color=None) -> np.ndarray:
    """The contract's vertex record: float32 x y z nx ny nz ref_x ref_y ref_z
    [radius confidence] [uint32 id] [uchar red green blue]; `color` (N, 3) RGB, 0..255."""
    n = len(position)
    fields = [(name, "<f4") for name in VERTEX_FIELDS]
    if radius is not None:
        fields += [(name, "<f4") for name in SURFEL_FIELDS]
    if ids is not None:
        fields.append(("id", "<u4"))
    if color is not None:
        fields += [(name, "u1") for name in COLOR_FIELDS]
    table = np.empty(n, dtype=fields)
    for i, name in enumerate("xyz"):
        table[name] = position[:, i]
        table["n" + name] = normal[:, i]
        table["ref_" + name] = ref_position[:, i]
    if radius is not None:
        table["radius"], table["confidence"] = radius, confidence
    if ids is not None:
        table["id"] = ids
    if color is not None:
        rgb = np.clip(np.rint(color), 0, 255).astype(np.uint8)
        for i, name in enumerate(COLOR_FIELDS):
            table[name] = rgb[:, i]
    return table


def mesh_table(vertices, normals, color=None) -> np.ndarray:
    """A mesh's vertex record (CONTRACT.md, model_mesh.ply): float32 x y z nx ny nz [uchar red green blue]."""
    fields = [(name, "<f4") for name in VERTEX_FIELDS[:6]]
    if color is not None:
        fields += [(name, "u1") for name in COLOR_FIELDS]
    table = np.empty(len(vertices), dtype=fields)
    for i, name in enumerate("xyz"):
        table[name], table["n" + name] = vertices[:, i], normals[:, i]
    if color is not None:
        for i, name in enumerate(COLOR_FIELDS):
            table[name] = color[:, i]
    return table


def write_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary file beside `path`, then rename over it: readers never see half a file."""
    write_atomic_with(path, lambda f: f.write(data))


def write_atomic_with(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """write(f) into a temporary file beside `path`, then rename it over `path`. A write that
    fails (full disk, no permission) leaves `path` as it was and raises OutputError."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(path, f"cannot write ({exc.strerror or exc.__class__.__name__})") from None


def encode_ply(vertices: np.ndarray, faces: np.ndarray | None = None) -> bytes:
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    for name in vertices.dtype.names:
        header.append(f"property {_PLY_TYPES[vertices.dtype[name].str[1:]]} {name}")
    body = [vertices.astype(vertices.dtype.newbyteorder("<")).tobytes()]
    if faces is not None:
        faces = np.asarray(faces, dtype="<i4").reshape(-1, 3)
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        packed = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        packed["n"], packed["v"] = 3, faces
        body.append(packed.tobytes())
    return ("\n".join(header) + "\nend_header\n").encode("ascii") + b"".join(body)


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
    write_atomic(path, encode_ply(vertices, faces))


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(vertex table, faces (F, 3) or None) of a binary little-endian PLY with triangle faces."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    elements, current = [], None
    for line in lines:
        parts = line.split()
        if parts[:1] == ["element"]:
            current = [parts[1], int(parts[2]), []]
            elements.append(current)
        elif parts[:1] == ["property"]:
            current[2].append(parts[1:])
    offset, vertices, faces = end, None, None
    for name, count, props in elements:
        if name == "vertex":
            dtype = np.dtype([(p[1], "<" + _NUMPY_TYPES[p[0]]) for p in props])
            vertices = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
            offset += dtype.itemsize * count
        elif name == "face":
            _, count_type, index_type, _ = props[0]
            dtype = np.dtype([("n", _NUMPY_TYPES[count_type]), ("v", "<" + _NUMPY_TYPES[index_type], (3,))])
            faces = np.frombuffer(data, dtype=dtype, count=count, offset=offset)["v"].copy()
            offset += dtype.itemsize * count
    return vertices, faces
