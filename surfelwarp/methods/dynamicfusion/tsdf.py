"""Canonical TSDF volume and non-rigid projective fusion (DynamicFusion Sec. 3.2, Eq. 3-5).

The volume lives in world coordinates (the camera frame of the first frame). Fusion takes voxel
centres that the caller has already warped into the live scene (W(x_c) x_c, still in world), so
this module knows nothing about the warp field. TSDF values are stored normalised by the
truncation distance, in [-1, 1]: positive in front of the surface (free space), negative behind.
Unobserved voxels hold tsdf 1 and weight 0. With colour input each voxel also holds an RGB
running average, fused with the tsdf's weights.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.measure import marching_cubes

from surfelwarp.geometry.camera import Intrinsics

CHUNK_VOXELS = 1 << 20    # temporaries of fuse() stay near 60 MB whatever the volume size


@dataclass(frozen=True)
class TSDFParams:
    voxel_size_m: float = 0.004
    # tau: 3 voxels. It must exceed the depth noise of the sensor (a few mm at 1-2 m) and the
    # voxel size, yet stay below the thickness of thin parts (fingers, ~15 mm) so the two sides
    # of a thin part do not overwrite each other; KinectFusion-style systems use 2-5 voxels.
    truncation_m: float = 0.012
    # Eq. 5's cap comes from KinectFusion (the paper's ref. [18]); neither paper fixes a value.
    # 100 frames of full weight (~170 at the node weight of a surface voxel, ~0.6) averages out
    # sensor noise yet lets the canonical model still follow slow change.
    max_weight: float = 100.0
    margin_m: float = 0.1            # added on every side of the first frame's bounding box, and of
                                     # the depth seen outside the volume when it grows
    max_voxels: int = 8_000_000      # larger boxes get coarser voxels (see TSDFVolume.from_points)
                                     # and a truncation of at least two of them

    ZERO_OK = {"margin_m"}
    AT_MOST = {"max_voxels": 200_000_000, "margin_m": 2.0}

    def problems(self) -> dict[str, bool]:
        return {"truncation_m": self.truncation_m < 2 * self.voxel_size_m and
                "must be at least two voxels (2 x voxel_size_m)"}


@dataclass
class TSDFVolume:
    """Voxel (i, j, k) has its centre at origin + (i, j, k) * voxel_size (world frame, metres)."""
    origin: np.ndarray       # (3,) float64, centre of voxel (0, 0, 0)
    voxel_size: float
    tsdf: np.ndarray         # (X, Y, Z) float32, normalised by the truncation distance
    weight: np.ndarray       # (X, Y, Z) float32, 0 = never observed
    color: np.ndarray | None = None         # (X, Y, Z, 3) float32 RGB 0..255; None: no colour input
    # (X, Y, Z) float32 the weight of the observations that had colour (== weight when every frame
    # has it): a voxel first fused without colour takes its first colour whole.
    color_weight: np.ndarray | None = None

    @classmethod
    def empty(cls, origin, dims, voxel_size: float, color: bool = False) -> "TSDFVolume":
        """float32 colour (16 bytes a voxel with its weight): rounding to bytes would freeze a
        running average whose weight reaches max_weight (a step of 1/100 of the difference)."""
        dims = tuple(int(d) for d in dims)
        return cls(origin=np.asarray(origin, np.float64).reshape(3), voxel_size=float(voxel_size),
                   tsdf=np.ones(dims, np.float32), weight=np.zeros(dims, np.float32),
                   color=np.zeros(dims + (3,), np.float32) if color else None,
                   color_weight=np.zeros(dims, np.float32) if color else None)

    @classmethod
    def from_points(cls, points_world: np.ndarray, params: TSDFParams = TSDFParams(),
                    color: bool = False) -> "TSDFVolume":
        """The axis-aligned box of the (finite) points plus params.margin_m on each side; with
        `color`, voxels hold colour too.

        If the box would need more than params.max_voxels voxels at params.voxel_size_m, the
        voxel size grows until it fits (the volume's own voxel_size is the one in force).
        """
        p = np.asarray(points_world, np.float64).reshape(-1, 3)
        p = p[np.isfinite(p).all(1)]
        if len(p) == 0:
            raise ValueError("no finite points to bound the volume")
        lo = p.min(0) - params.margin_m
        hi = p.max(0) + params.margin_m
        voxel = float(params.voxel_size_m)
        while True:
            dims = np.ceil((hi - lo) / voxel).astype(np.int64) + 1
            if np.prod(dims) <= params.max_voxels:
                break
            voxel *= max((np.prod(dims) / params.max_voxels) ** (1 / 3), 1.001)
        # Centre the grid on the box so the margin is even on both sides.
        origin = 0.5 * (lo + hi) - 0.5 * (dims - 1) * voxel
        return cls.empty(origin, dims, voxel, color)

    def truncation_m(self, params: TSDFParams) -> float:
        """The truncation in force: the configured one, but at least two of this volume's voxels
        (a volume coarsened to fit max_voxels keeps a band two voxels wide; thinner, the zero
        crossing falls between voxels and the surface breaks up)."""
        return max(params.truncation_m, 2.0 * self.voxel_size)

    def padding(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxels to add before and after the grid along each axis to cover the world box lo..hi."""
        dims = np.array(self.dims)
        first = np.floor((np.asarray(lo, np.float64) - self.origin) / self.voxel_size).astype(np.int64)
        last = np.ceil((np.asarray(hi, np.float64) - self.origin) / self.voxel_size).astype(np.int64)
        return np.maximum(-first, 0), np.maximum(last - (dims - 1), 0)

    def padded(self, before: np.ndarray, after: np.ndarray) -> tuple["TSDFVolume", tuple[slice, ...]]:
        """This volume on a grid extended by `before` and `after` voxels per axis (same voxels,
        new ones unobserved), and where the old grid sits in the new one."""
        before, dims = np.asarray(before, np.int64), np.array(self.dims)
        grown = TSDFVolume.empty(self.origin - before * self.voxel_size, dims + before + np.asarray(after),
                                 self.voxel_size, color=self.color is not None)
        place = tuple(slice(int(b), int(b + d)) for b, d in zip(before, dims))
        for name in ("tsdf", "weight", "color", "color_weight"):
            if getattr(self, name) is not None:
                getattr(grown, name)[place] = getattr(self, name)
        return grown, place

    @property
    def dims(self) -> tuple[int, int, int]:
        return self.tsdf.shape

    @property
    def num_voxels(self) -> int:
        return self.tsdf.size

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.tsdf, self.weight, self.color, self.color_weight) if a is not None)

    def voxel_centres(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """World centres (n, 3) float32 of flat voxels start..stop (flat order = tsdf.ravel())."""
        stop = self.num_voxels if stop is None else min(stop, self.num_voxels)
        _, y, z = self.dims
        slab = y * z
        i0, i1 = start // slab, -(-stop // slab)
        # Built by broadcasting over whole x-slabs (integer division per voxel is ~10x slower).
        out = np.empty((i1 - i0, y, z, 3), np.float32)
        for axis, (lo, size) in enumerate(((i0, i1 - i0), (0, y), (0, z))):
            shape = [1, 1, 1]
            shape[axis] = size
            out[..., axis] = (self.origin[axis] + np.arange(lo, lo + size) * self.voxel_size).reshape(shape)
        return out.reshape(-1, 3)[start - i0 * slab:stop - i0 * slab]


@dataclass(frozen=True)
class FuseResult:
    visible: int     # voxels projecting into the image onto a valid depth
    updated: int     # of those, voxels with psdf > -tau and a positive weight (Eq. 4)


def fuse(volume: TSDFVolume, warped_centres_world: np.ndarray | None, voxel_weight,
         T_world_to_camera: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics,
         params: TSDFParams = TSDFParams(), chunk: int = CHUNK_VOXELS,
         voxels: np.ndarray | None = None, color: np.ndarray | None = None) -> FuseResult:
    """Fuse one depth map into `volume` in place (DynamicFusion Eq. 3-5).

    warped_centres_world: (V, 3) voxel centres moved by the warp, in world coordinates, flat
    order of volume.tsdf; None means the identity warp (rigid fusion). voxel_weight: (V,) or a
    scalar, the weight w(x) of this observation (e.g. node_distance_weight). Each warped centre
    goes into the camera, is projected to the nearest pixel u, and psdf = D(u) - z (the depth of
    the back-projected pixel minus the voxel's depth, along the optical axis). Voxels with
    psdf > -tau take v' = (v w + min(1, psdf/tau) w_new) / (w + w_new), w' = min(w + w_new, w_max).
    voxels: optional flat indices of the only voxels to consider (the caller knows the others
    cannot be fused); warped centres and weights are then given for those voxels, in that order.
    color: (H, W, 3) RGB registered to depth_m; fused into volume.color (if it has colour) with
    the same weights and cap as the tsdf, for the voxels within the band (|psdf| < tau).
    """
    if voxels is not None:
        if warped_centres_world is None:
            raise ValueError("a voxel subset needs its warped centres")
        voxels = np.asarray(voxels, np.int64).reshape(-1)
    n = volume.num_voxels if voxels is None else len(voxels)
    if warped_centres_world is not None:
        warped_centres_world = np.asarray(warped_centres_world).reshape(-1, 3)
        if len(warped_centres_world) != n:
            raise ValueError(f"{len(warped_centres_world)} warped centres for {n} voxels")
    scalar_weight = np.ndim(voxel_weight) == 0
    if not scalar_weight:
        voxel_weight = np.asarray(voxel_weight, np.float32).reshape(-1)
        if len(voxel_weight) != n:
            raise ValueError(f"{len(voxel_weight)} voxel weights for {n} voxels")
    depth = np.asarray(depth_m, np.float32)
    height, width = depth.shape
    T = np.asarray(T_world_to_camera, np.float64)
    fx, fy, cx, cy = (np.float32(c) for c in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy))
    tau = np.float32(volume.truncation_m(params))
    w_max = np.float32(params.max_weight)
    depth_flat = depth.reshape(-1)
    tsdf = volume.tsdf.reshape(-1)       # views: updates land in the volume
    weight = volume.weight.reshape(-1)
    color_flat = None if color is None or volume.color is None else np.asarray(color, np.float32).reshape(-1, 3)
    visible = updated = 0
    for start, stop, (x, y, z) in _camera_coords(volume, warped_centres_world, T, chunk):
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(fx * x / z + cx)
            v = np.rint(fy * y / z + cy)
        # Comparisons are False for NaN, so NaN coordinates drop out here.
        ok = (z > 0) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
        idx = np.flatnonzero(ok)
        pixel = v[idx].astype(np.int64) * width + u[idx].astype(np.int64)
        d = depth_flat[pixel]
        good = d > 0                       # also drops NaN depth
        idx, d, pixel = idx[good], d[good], pixel[good]
        visible += len(idx)
        psdf = d - z[idx]
        w_new = np.full(len(idx), voxel_weight, np.float32) if scalar_weight else voxel_weight[start:stop][idx]
        keep = (psdf > -tau) & (w_new > 0)
        idx, psdf, w_new = idx[keep], psdf[keep], w_new[keep]
        updated += len(idx)
        g = idx + start if voxels is None else voxels[idx + start]
        if color_flat is not None:
            # Only within the band: a voxel farther in front of its pixel's surface is free space,
            # and that colour is not its own (a silhouette's voxels would take the background's).
            band = psdf < tau
            _fuse_color(volume, g[band], color_flat[pixel[keep][band]], w_new[band], w_max)
        w_old = weight[g]
        w_sum = w_old + w_new
        tsdf[g] = (tsdf[g] * w_old + np.minimum(np.float32(1), psdf / tau) * w_new) / w_sum
        weight[g] = np.minimum(w_sum, w_max)
    return FuseResult(visible=int(visible), updated=int(updated))


def _fuse_color(volume: TSDFVolume, g: np.ndarray, rgb: np.ndarray, w_new: np.ndarray, w_max: np.float32) -> None:
    """Eq. 5's running average for the colour of flat voxels g, in place."""
    color, color_weight = volume.color.reshape(-1, 3), volume.color_weight.reshape(-1)
    w_old = color_weight[g]
    w_sum = w_old + w_new
    old = color[g]
    color[g] = old + (w_new / w_sum)[:, None] * (rgb - old)     # a voxel's first colour exactly
    color_weight[g] = np.minimum(w_sum, w_max)


def _camera_coords(volume: TSDFVolume, warped: np.ndarray | None, T: np.ndarray, chunk: int):
    """Yield (start, stop, (x, y, z)) camera-frame float32 coordinates of flat voxel chunks.

    Per-component products instead of `p @ R.T`: numpy's matmul with an inner size of 3 is
    about 20x slower. The identity warp needs no centres at all: a voxel's camera position is
    separable, A[i] + B[j] + C[k], so whole x-slabs are built by broadcasting.
    """
    R = T[:3, :3]
    t = T[:3, 3]
    if warped is not None:
        n = len(warped)
        Rf, tf = R.astype(np.float32), t.astype(np.float32)
        for start in range(0, n, chunk):
            stop = min(start + chunk, n)
            p = np.asarray(warped[start:stop], np.float32)
            yield start, stop, tuple(p[:, 0] * Rf[r, 0] + p[:, 1] * Rf[r, 1] + p[:, 2] * Rf[r, 2] + tf[r]
                                     for r in range(3))
        return
    X, Y, Z = volume.dims
    steps = [np.arange(d) * volume.voxel_size for d in (X, Y, Z)]
    base = R @ volume.origin + t
    slab = max(1, chunk // (Y * Z))
    for i0 in range(0, X, slab):
        i1 = min(i0 + slab, X)
        coords = tuple((base[r] + steps[0][i0:i1, None, None] * R[r, 0] + steps[1][None, :, None] * R[r, 1]
                        + steps[2][None, None, :] * R[r, 2]).astype(np.float32).reshape(-1)
                       for r in range(3))
        yield i0 * Y * Z, i1 * Y * Z, coords


def node_distance_weight(voxel_centres: np.ndarray, node_positions: np.ndarray, knn: np.ndarray,
                         node_radius_m=0.025, chunk: int = CHUNK_VOXELS) -> np.ndarray:
    """Per-voxel fusion weight from the mean distance to its k nearest nodes (Sec. 3.2).

    The paper writes w(x) "proportional to" (1/k) sum_i ||dg^i - x_c|| and uses that mean
    distance as a proxy for the warp's uncertainty; taken literally the weight would grow with
    the uncertainty, so we use a decreasing function of it, with the distances measured in units
    of each node's radius dg_w (scalar or (n,) array, metres):
        w(x) = exp(-dbar^2 / 2),  dbar = (1/k) sum_{i in N(x)} ||dg_v^i - x|| / dg_w^i.
    A voxel on the surface among nodes spaced by their radius gets ~0.6; one three radii away
    from all nodes gets ~0.01. knn (V, k) holds node indices; negative entries are empty slots
    and are left out of the mean; a voxel with no node gets weight 0. Returns (V,) float32.
    """
    x = np.asarray(voxel_centres, np.float32).reshape(-1, 3)
    nodes = np.asarray(node_positions, np.float32).reshape(-1, 3)
    knn = np.asarray(knn)
    if knn.ndim == 1:
        knn = knn[:, None]
    if len(knn) != len(x):
        raise ValueError(f"knn has {len(knn)} rows for {len(x)} voxels")
    radius = np.broadcast_to(np.asarray(node_radius_m, np.float32), (len(nodes),))
    out = np.zeros(len(x), np.float32)
    if len(nodes) == 0:
        return out
    # One pass per neighbour slot over contiguous columns: a (V, k, 3) gather is ~10x slower.
    node_cols = [np.ascontiguousarray(nodes[:, a]) for a in range(3)]
    for start in range(0, len(x), chunk):
        stop = min(start + chunk, len(x))
        xs = [np.ascontiguousarray(x[start:stop, a]) for a in range(3)]
        total = np.zeros(stop - start, np.float32)
        count = np.zeros(stop - start, np.int32)
        for slot in range(knn.shape[1]):
            k = knn[start:stop, slot]
            valid = k >= 0
            k = np.where(valid, k, 0)
            d2 = sum((col[k] - xa) ** 2 for col, xa in zip(node_cols, xs))
            total += np.where(valid, np.sqrt(d2) / radius[k], 0)
            count += valid
        dbar = total / np.maximum(count, 1)
        out[start:stop] = np.where(count > 0, np.exp(-0.5 * dbar * dbar), 0)
    return out


def _observed_gradient(tsdf: np.ndarray, observed: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """(N, 3) tsdf gradient at voxels ijk from observed neighbours only: central differences,
    one-sided where one neighbour is unobserved (its +1 is no measurement), 0 where both are."""
    shape = np.array(tsdf.shape)
    grad = np.zeros(ijk.shape, np.float64)
    centre = tsdf[ijk[:, 0], ijk[:, 1], ijk[:, 2]].astype(np.float64)
    for axis in range(3):
        ends = []
        for step in (-1, 1):
            nb = ijk.copy()
            nb[:, axis] += step
            inside = (nb[:, axis] >= 0) & (nb[:, axis] < shape[axis])
            nb[:, axis] = np.clip(nb[:, axis], 0, shape[axis] - 1)
            ok = inside & observed[nb[:, 0], nb[:, 1], nb[:, 2]]
            ends.append((ok, tsdf[nb[:, 0], nb[:, 1], nb[:, 2]].astype(np.float64)))
        (ok_lo, lo), (ok_hi, hi) = ends
        grad[:, axis] = np.where(ok_lo & ok_hi, 0.5 * (hi - lo),
                                 np.where(ok_hi, hi - centre, np.where(ok_lo, centre - lo, 0.0)))
    return grad


def extract_mesh(volume: TSDFVolume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero level set by marching cubes (skimage, Lewiner), only between observed voxels.

    Returns vertices (N, 3) float32 world, faces (F, 3) int32 and unit normals (N, 3) float32
    pointing out of the surface toward positive tsdf (the side the camera saw). Faces wind
    counter-clockwise seen from that side. A vertex lies on the grid edge between two voxels;
    it is kept only if both have weight > 0, so the step from observed negative values to the
    untouched +1 behind the surface yields no spurious sheet.
    """
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))
    observed = volume.weight > 0
    if not observed.any():
        return empty
    # Marching cubes only over the observed bounding box (plus one voxel), which is often small.
    axes = [np.flatnonzero(observed.any(axis=tuple(a for a in range(3) if a != i))) for i in range(3)]
    lo = np.array([max(a[0] - 1, 0) for a in axes])
    hi = np.array([min(a[-1] + 2, s) for a, s in zip(axes, volume.dims)])
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    tsdf, obs = volume.tsdf[box], observed[box]
    if min(tsdf.shape) < 2 or not (tsdf.min() < 0 < tsdf.max()):
        return empty
    try:
        verts, faces, _, _ = marching_cubes(tsdf, level=0.0, allow_degenerate=False)
    except RuntimeError:   # no surface crossing
        return empty
    a = np.floor(verts).astype(np.int64)
    b = np.ceil(verts).astype(np.int64)
    ok = obs[a[:, 0], a[:, 1], a[:, 2]] & obs[b[:, 0], b[:, 1], b[:, 2]]
    faces = faces[ok[faces].all(1)]
    used = np.zeros(len(verts), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    verts = verts[used].astype(np.float64)
    faces = remap[faces]
    # Normals: the tsdf gradient (its ascent, toward the camera side) at the edge's two voxels,
    # interpolated along the edge like the vertex itself.
    a, b = a[used], b[used]
    frac = np.abs(verts - a).sum(1, keepdims=True)
    grad = (1 - frac) * _observed_gradient(tsdf, obs, a) + frac * _observed_gradient(tsdf, obs, b)
    normals = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
    tri = verts[faces]
    geometric = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = (geometric * normals[faces].sum(1)).sum(1) < 0
    faces[flip] = faces[flip][:, ::-1]
    world = volume.origin + (verts + lo) * volume.voxel_size
    return world.astype(np.float32), faces.astype(np.int32), normals.astype(np.float32)


def sample_color(volume: TSDFVolume, points_world: np.ndarray) -> np.ndarray:
    """(N, 3) float32 RGB at world points: trilinear over the 8 surrounding voxels that were seen
    in colour, renormalised over them (0 where none was). A marching-cubes vertex lies on the
    edge between two voxels, so this is the colour interpolated along that edge."""
    g = (np.asarray(points_world, np.float64).reshape(-1, 3) - volume.origin) / volume.voxel_size
    dims = np.array(volume.dims)
    base = np.clip(np.floor(g).astype(np.int64), 0, np.maximum(dims - 2, 0))
    frac = np.clip(g - base, 0.0, 1.0)
    total = np.zeros((len(g), 3))
    weight_sum = np.zeros(len(g))
    for corner in np.ndindex(2, 2, 2):
        ijk = np.minimum(base + corner, dims - 1)
        w = np.prod(np.where(np.array(corner, bool), frac, 1.0 - frac), axis=1)
        w = w * (volume.color_weight[ijk[:, 0], ijk[:, 1], ijk[:, 2]] > 0)
        total += w[:, None] * volume.color[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        weight_sum += w
    return (total / np.maximum(weight_sum, 1e-12)[:, None]).astype(np.float32)
