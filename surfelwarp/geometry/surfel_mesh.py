"""A triangle mesh of a surfel model: a signed distance sampled near the surfels, then marching cubes.

Each voxel within a band of the surfels takes the distance to the tangent planes of its nearest
surfels (n . (x - p), weighted by a Gaussian of the distance to p): the zero crossing lies on
the surfels' planes, so vertices are as accurate as the surfels are, whatever the voxel size on
smooth surface. Only voxels near a surfel carry a value, and a cube with any corner without one
makes no triangle: surface is never made up across a gap wider than about two voxels (between
two fingers) or behind the band. Marching cubes is scikit-image's, run on chunks of the grid that
hold surfels, so a room does not need a dense volume; the chunks' shared vertices are merged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree
from skimage.measure import marching_cubes


@dataclass(frozen=True)
class SurfelMesh:
    vertices: np.ndarray      # (V, 3) float32
    normals: np.ndarray       # (V, 3) float32, unit, from the surfels
    faces: np.ndarray         # (F, 3) int32, counter-clockwise seen from the normals' side
    colors: np.ndarray | None = None   # (V, 3) uint8 RGB, where the surfels have colour


def voxel_size_for(radius: np.ndarray) -> float:
    """The surfels' median radius: the grid resolves what the surfels do, and no finer."""
    with np.errstate(all="ignore"):
        r = np.asarray(radius, np.float64)
        r = r[np.isfinite(r) & (r > 0)]
    return float(np.clip(np.median(r), 5e-4, 0.05)) if len(r) else 0.004


def mesh_of(table: np.ndarray, faces: np.ndarray | None = None, voxel_m: float | None = None) -> SurfelMesh:
    """The mesh of a PLY vertex table (fields x y z nx ny nz [radius] [red green blue]): its own
    faces if it has them (a volumetric model), else mesh_surfels at voxel_m (default: the
    surfels' median radius)."""
    stack = lambda *names: np.stack([table[n] for n in names], -1)   # noqa: E731
    points, normals = stack("x", "y", "z").astype(np.float32), stack("nx", "ny", "nz").astype(np.float32)
    colors = stack("red", "green", "blue").astype(np.uint8) if "red" in table.dtype.names else None
    if faces is not None:
        return SurfelMesh(points, normals, np.asarray(faces, np.int32).reshape(-1, 3), colors)
    if voxel_m is None:
        voxel_m = voxel_size_for(table["radius"]) if "radius" in table.dtype.names else 0.004
    return mesh_surfels(points, normals, voxel_m, colors)


def mesh_surfels(points: np.ndarray, normals: np.ndarray, voxel_m: float, colors: np.ndarray | None = None,
                 k: int = 8, chunk: int = 64) -> SurfelMesh:
    """Points and unit normals (N, 3) (any frame, metres) -> SurfelMesh in the same frame."""
    # Damaged or diverged surfels (non-finite, or kilometres away) are no surface.
    with np.errstate(all="ignore"):
        points, normals = np.asarray(points, np.float32), np.asarray(normals, np.float32)
        length = np.linalg.norm(normals, axis=1)
        keep = (np.abs(points) < 1e3).all(1) & (np.abs(length - 1) < 0.1)
    points, normals = np.ascontiguousarray(points[keep]), normals[keep]
    colors = None if colors is None else np.asarray(colors)[keep]
    empty = SurfelMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32),
                       None if colors is None else np.zeros((0, 3), np.uint8))
    if len(points) < 4:
        return empty
    tree = KDTree(points)
    cells = _cells_near(np.floor(points / voxel_m).astype(np.int64))
    centres = (cells * voxel_m).astype(np.float32)
    k = min(k, len(points))
    d, nn = tree.query(centres, k=k)
    d, nn = d.reshape(len(cells), k), nn.reshape(len(cells), k)
    near = d[:, 0] <= 2.0 * voxel_m
    cells, centres, d, nn = cells[near], centres[near], d[near], nn[near]
    w = np.exp(-0.5 * (d / voxel_m) ** 2) * (d <= 2.5 * voxel_m)
    plane = np.einsum("vki,vki->vk", normals[nn], centres[:, None, :] - points[nn])
    sdf = np.sum(w * plane, 1) / np.maximum(np.sum(w, 1), 1e-12)

    vertices, faces = _chunked_marching_cubes(cells, sdf.astype(np.float32), voxel_m, chunk)
    if len(faces) == 0:
        return empty
    _, vn = tree.query(vertices, k=k)
    vn = vn.reshape(len(vertices), k)
    vd = np.linalg.norm(points[vn] - vertices[:, None, :], axis=2)
    # Past the surfels' border the planes extrapolate: faces end within a voxel of a surfel.
    faces = faces[np.all(vd[faces, 0] <= voxel_m, axis=1)]
    if len(faces) == 0:
        return empty
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    vertices, vn, vd = vertices[used], vn[used], vd[used]
    vw = np.exp(-0.5 * (vd / voxel_m) ** 2) + 1e-12
    n = np.einsum("vk,vki->vi", vw, normals[vn])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    # Wind faces counter-clockwise about the surfels' normals.
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if np.sum(np.einsum("fi,fi->f", face_n, n[faces].sum(1))) < 0:
        faces = faces[:, ::-1]
    rgb = None
    if colors is not None:
        rgb = np.clip(np.rint(np.einsum("vk,vki->vi", vw, np.asarray(colors, np.float32)[vn]) /
                              vw.sum(1, keepdims=True)), 0, 255).astype(np.uint8)
    return SurfelMesh(vertices, n.astype(np.float32), np.ascontiguousarray(faces, np.int32), rgb)


def _cells_near(base: np.ndarray) -> np.ndarray:
    """The grid points (M, 3) within -1..+2 cells of the surfels' cells `base` (N, 3), each once,
    in lexicographic order. The 4x4x4 neighbourhood is three 4-wide steps, one axis at a time,
    on the cells packed into one integer each (64 neighbours of every surfel at once took
    ~2 s for 270k surfels)."""
    lo = base.min(0) - 1
    dims = base.max(0) + 3 - lo
    keys = np.unique(_packed(base, lo, dims))
    for stride in (dims[1] * dims[2], dims[2], 1):
        # Four sorted runs: a stable sort (timsort) merges them, faster than np.unique's hash.
        keys = np.sort((keys[None, :] + stride * np.arange(-1, 3)[:, None]).reshape(-1), kind="stable")
        keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])]
    return _unpacked(keys, lo, dims)


def _packed(rows: np.ndarray, lo: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """(N,) int64 keys of integer rows (N, 3) in lo .. lo + dims - 1, in their lexicographic order."""
    return ((rows[:, 0] - lo[0]) * dims[1] + (rows[:, 1] - lo[1])) * dims[2] + (rows[:, 2] - lo[2])


def _unpacked(keys: np.ndarray, lo: np.ndarray, dims: np.ndarray) -> np.ndarray:
    return np.stack([keys // (dims[1] * dims[2]), keys // dims[2] % dims[1], keys % dims[2]], 1) + lo


def unique_rows(rows: np.ndarray, **options):
    """np.unique(rows, axis=0, **options) for (N, 3) integer rows, the same arrays: the rows
    packed into one int64 each in lexicographic order when they fit (numpy sorts rows as
    opaque records, several times slower), else by rows."""
    lo = rows.min(0) if len(rows) else np.zeros(3, np.int64)
    dims = (rows.max(0) - lo + 1) if len(rows) else np.ones(3, np.int64)
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0 ** 62:
        return np.unique(rows, axis=0, **options)
    out = np.unique(_packed(rows, lo, dims), **options)
    out = out if isinstance(out, tuple) else (out,)
    unique = _unpacked(out[0], lo, dims)
    return (unique,) + out[1:] if len(out) > 1 else unique


def _chunked_marching_cubes(cells: np.ndarray, sdf: np.ndarray, voxel_m: float,
                            chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes over the sparse samples (integer cells, values), chunk^3 cubes at a time;
    cubes with a corner without a sample make no triangle. Vertices (V, 3) float32, faces."""
    lo = cells.min(0)
    local = cells - lo
    # A sample on a chunk's lower face is also on the upper face of the chunk before it.
    owners, rows = [local // chunk], [np.arange(len(local))]
    for axis_set in range(1, 8):
        axes = [a for a in range(3) if axis_set >> a & 1]
        shared = np.all([(local[:, a] % chunk == 0) & (local[:, a] > 0) for a in axes], axis=0)
        owner = local[shared] // chunk
        owner[:, axes] -= 1
        owners.append(owner)
        rows.append(np.flatnonzero(shared))
    owner, row = np.concatenate(owners), np.concatenate(rows)
    keys, inverse = unique_rows(owner, return_inverse=True)
    order = np.argsort(inverse.reshape(-1), kind="stable")
    bounds = np.searchsorted(inverse.reshape(-1)[order], np.arange(len(keys) + 1))
    all_vertices, all_faces, count = [], [], 0
    for c, key in enumerate(keys):
        start = key * chunk
        mine = row[order[bounds[c]:bounds[c + 1]]]
        idx = local[mine] - start
        values = np.ones((chunk + 1,) * 3, np.float32)
        known = np.zeros((chunk + 1,) * 3, bool)
        values[tuple(idx.T)] = sdf[mine]
        known[tuple(idx.T)] = True
        if not (values[known].min() < 0 < values[known].max()):
            continue
        verts, faces, _, _ = marching_cubes(values, level=0.0, allow_degenerate=False)
        # A vertex lies on a grid edge; both ends must carry samples.
        a = np.floor(verts).astype(np.int64)
        b = np.minimum(np.ceil(verts).astype(np.int64), chunk)
        ok = known[tuple(a.T)] & known[tuple(b.T)]
        faces = faces[ok[faces].all(1)]
        if len(faces) == 0:
            continue
        all_vertices.append(((verts + start + lo) * voxel_m).astype(np.float32))
        all_faces.append(faces + count)
        count += len(verts)
    if not all_faces:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    vertices, faces = np.concatenate(all_vertices), np.concatenate(all_faces)
    # Merge the vertices two chunks made on their shared face, and drop unused ones.
    q = np.rint(vertices / voxel_m * 1024).astype(np.int64)
    _, first, remap = unique_rows(q, return_index=True, return_inverse=True)
    faces = remap.reshape(-1)[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    used, faces = np.unique(faces, return_inverse=True)
    return vertices[first][used], faces.reshape(-1, 3)
