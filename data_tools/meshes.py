"""Triangle-mesh building blocks for the synthetic scenes: grids, surfaces of revolution,
isometric bending of strips, vertex normals.

Meshes are (vertices (V, 3) float64, faces (F, 3) int32). Surfaces of revolution have their
axis along +y; flat grids lie in the x-y plane.
"""
from __future__ import annotations

import numpy as np


def grid_faces(rows: int, cols: int, wrap_cols: bool = False, wrap_rows: bool = False) -> np.ndarray:
    """Two triangles per cell of a rows x cols vertex grid stored row-major."""
    r = np.arange(rows if wrap_rows else rows - 1)
    c = np.arange(cols if wrap_cols else cols - 1)
    r, c = np.meshgrid(r, c, indexing="ij")
    r1, c1 = (r + 1) % rows, (c + 1) % cols
    a, b, d, e = r * cols + c, r * cols + c1, r1 * cols + c, r1 * cols + c1
    return np.concatenate([np.stack([a, d, b], -1).reshape(-1, 3),
                           np.stack([b, d, e], -1).reshape(-1, 3)]).astype(np.int32)


def plane(width: float, height: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A width x height rectangle centred at the origin in the x-y plane."""
    nx = int(np.ceil(width / spacing)) + 1
    ny = int(np.ceil(height / spacing)) + 1
    x, y = np.meshgrid(np.linspace(-width / 2, width / 2, nx), np.linspace(-height / 2, height / 2, ny))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], -1)
    return vertices, grid_faces(ny, nx)


def resample_polyline(points: np.ndarray, spacing: float, closed: bool = False) -> np.ndarray:
    """Points along a 2D polyline with steps of at most `spacing` (every corner is kept)."""
    pts = np.asarray(points, dtype=np.float64)
    if closed:
        pts = np.vstack([pts, pts[:1]])
    out = []
    for p, q in zip(pts[:-1], pts[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / spacing)))
        out.append(p + (q - p) * (np.arange(n) / n)[:, None])
    if not closed:
        out.append(pts[-1:])
    return np.vstack(out)


def revolve(profile: np.ndarray, spacing: float, closed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Surface swept by a (radius, y) profile turning about the y axis.

    Profile points with radius ~0 become single pole vertices; `closed` joins the last
    profile point back to the first (a torus).
    """
    profile = resample_polyline(profile, spacing, closed)
    radius, y = profile[:, 0], profile[:, 1]
    segments = max(8, int(np.ceil(2 * np.pi * radius.max() / spacing)))
    phi = 2 * np.pi * np.arange(segments) / segments
    pole = radius < 1e-9
    vertices, ring_start = [], []
    count = 0
    for r, h, is_pole in zip(radius, y, pole):
        ring_start.append(count)
        if is_pole:
            vertices.append([[0.0, h, 0.0]])
            count += 1
        else:
            vertices.append(np.stack([r * np.cos(phi), np.full(segments, h), -r * np.sin(phi)], -1))
            count += segments
    faces = []
    k = np.arange(segments)
    pairs = list(zip(range(len(profile) - 1), range(1, len(profile))))
    if closed:
        pairs.append((len(profile) - 1, 0))
    for i, j in pairs:
        a, b = ring_start[i], ring_start[j]
        if pole[i] and pole[j]:
            continue
        if pole[i]:
            faces.append(np.stack([np.full(segments, a), b + k, b + (k + 1) % segments], -1))
        elif pole[j]:
            faces.append(np.stack([a + k, np.full(segments, b), a + (k + 1) % segments], -1))
        else:
            faces.append(np.stack([a + k, b + k, a + (k + 1) % segments], -1))
            faces.append(np.stack([a + (k + 1) % segments, b + k, b + (k + 1) % segments], -1))
    return np.vstack(vertices), np.vstack(faces).astype(np.int32)


def arc(center: tuple[float, float], radius: float, start: float, stop: float, spacing: float) -> np.ndarray:
    """Points (r, y) at most `spacing` apart on a circular arc in the profile plane, angles in
    radians from +r."""
    t = np.linspace(start, stop, int(np.ceil(radius * abs(stop - start) / spacing)) + 1)
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], -1)


def capsule(radius: float, length: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder of the given radius along y in [0, length] closed by hemispheres."""
    bottom = arc((0.0, 0.0), radius, -np.pi / 2, 0.0, spacing)
    top = arc((0.0, length), radius, 0.0, np.pi / 2, spacing)
    bottom[0, 0] = top[-1, 0] = 0.0
    return revolve(np.vstack([bottom, top]), spacing)


def sphere(radius: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    profile = arc((0.0, 0.0), radius, -np.pi / 2, np.pi / 2, spacing)
    profile[[0, -1], 0] = 0.0
    return revolve(profile, spacing)


def rounded_cylinder(radius: float, height: float, fillet: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder along y in [0, height] with flat caps and rounded rims."""
    profile = np.vstack([[[0.0, 0.0]],
                         arc((radius - fillet, fillet), fillet, -np.pi / 2, 0.0, spacing),
                         arc((radius - fillet, height - fillet), fillet, 0.0, np.pi / 2, spacing),
                         [[0.0, height]]])
    return revolve(profile, spacing)


def torus(major: float, minor: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    profile = arc((major, 0.0), minor, 0.0, 2 * np.pi, spacing)[:-1]
    return revolve(profile, spacing, closed=True)


def merge(*meshes: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One mesh from several; also returns each vertex's part number (argument position)."""
    vertices, faces, part, offset = [], [], [], 0
    for i, (v, f) in enumerate(meshes):
        vertices.append(v)
        faces.append(f + offset)
        part.append(np.full(len(v), i, dtype=np.int16))
        offset += len(v)
    return np.vstack(vertices), np.vstack(faces).astype(np.int32), np.concatenate(part)


def bend_strip(s: np.ndarray, a: np.ndarray, s_grid: np.ndarray, theta_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Isometric bending of a straight strip in its (s, a) plane.

    The rest point s*e1 + a*e2 goes to C(s) + a*N(s), where the centre line C has arc length s
    and tangent angle theta(s) (theta = 0 everywhere is the identity). Past the ends of
    `s_grid` the strip continues straight along the end tangent. Returns the new (e1, e2)
    coordinates; the third coordinate is unchanged (the bending rulings).
    """
    t = np.stack([np.cos(theta_grid), np.sin(theta_grid)], -1)
    ds = np.diff(s_grid)[:, None]
    c = np.vstack([[[s_grid[0], 0.0]], [s_grid[0], 0.0] + np.cumsum(0.5 * (t[1:] + t[:-1]) * ds, axis=0)])
    sc = np.clip(s, s_grid[0], s_grid[-1])
    th = np.interp(sc, s_grid, theta_grid)
    cx = np.interp(sc, s_grid, c[:, 0]) + (s - sc) * np.cos(th)
    cy = np.interp(sc, s_grid, c[:, 1]) + (s - sc) * np.sin(th)
    return cx - a * np.sin(th), cy + a * np.cos(th)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, unit length (zero for unused vertices)."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(v)
    for corner in range(3):
        for axis in range(3):
            n[:, axis] += np.bincount(faces[:, corner], weights=fn[:, axis], minlength=len(v))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64), axis=1)
    n = int(e.max()) + 1
    key = np.unique(e[:, 0] * n + e[:, 1])
    return np.stack([key // n, key % n], -1)


def rotation(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R
