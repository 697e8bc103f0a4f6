"""Free-space evidence: model points where the depth camera saw through them are pulled back.

The data term pairs each model point with the depth at its pixel and so cannot see a model
that sticks out past the observed surface: a sheet sliding off its own edge, a limb sliding
along its axis past its tip. The camera sees through such points: at their pixel it measured
nothing, or a surface far behind them. This term (the visual-hull / foreground terms of
VolumeDeform, Fusion4D and the SurfelWarp authors' code) gives each such point the residual

    r = z / f * max(D(u, v) - margin_px, 0),

D the distance in pixels from its projection (u, v) to the nearest pixel where the camera saw
something at most depth_margin_m behind the point (a distance transform, one per depth layer
of layer_m), converted to metres at the point's depth z, under Huber's penalty.

Holes in real depth are not free space: an invalid region counts only where a disc of
hole_px fits in it (a morphological opening), so dropouts, edge pixels and the projector's
shadow beside a near object (up to 2 hole_px + 1 pixels wide) pull nothing, while the empty
space around an object does. Nor does one within occluder_px of depth in front of the point,
which may be a nearer surface seen edge-on and not measured. Pixels measured beyond the far
clip are free space in front of them, not holes. Points within border_px of the image edge
are not judged, nor points seen more than 60 degrees from face-on: sensors measure such
surface sparsely or not at all. (On the orbiting still life, template tracking with those
last two rules missing: ATE 1.13 cm, the pedestal's top pulled towards where a ring's rim,
seen edge-on, had no depth; with them 0.23 cm, as without the term.)

D is found by searching the pixels around each point, nearest first, with cv2's chamfer
metric in closed form: the points seen through are few and their D small (a 7-Scenes solve:
~1.8k of 118k points over ~90 layers, D below 7 px for 99 %), where a transform per layer
cost ~0.1 s a frame. A point with no consistent pixel within search_px falls back to the
transforms, which are kept as the reference the search is tested against.
"""
from __future__ import annotations

import copy
import functools
from dataclasses import dataclass

import cv2
import numpy as np

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.tracking.features import bounding_box
from surfelwarp.tracking.free_space_kernels import chamfer, row_minima, search, within_reach


@dataclass(frozen=True)
class SilhouetteParams:
    weight: float = 1.0             # per model point, against 1 for a depth pair (0: off)
    depth_margin_m: float = 0.03    # seen this far behind a point or farther: through it
    hole_px: int = 8                # invalid regions a disc of this radius fits in are free space
    margin_px: float = 1.5          # free space closer to the silhouette than this is not judged
    layer_m: float = 0.02           # depth layers of the distance transforms
    huber_m: float = 0.01           # Huber corner of the residual
    border_px: int = 12             # projections this close to the image edge are not judged
    min_view_cos: float = 0.5       # nor points whose normal is more than 60 deg from the view ray
    occluder_px: int = 24           # no depth this close to depth in front of a point: not free
    search_px: int = 32             # D up to this is searched for about each point (0: transforms only)

    ZERO_OK = {"weight", "depth_margin_m", "hole_px", "margin_px", "border_px", "min_view_cos", "occluder_px",
               "search_px"}
    UNIT = {"min_view_cos"}
    AT_MOST = {"hole_px": 256, "margin_px": 256, "border_px": 256, "occluder_px": 256, "search_px": 256}


# The chamfer distance of cv2's 5x5 mask is at least this fraction of the Euclidean one.
_CHAMFER_MIN = 0.95
_WINDOW_PAD_PX = 32    # the distance transforms' windows reach this far past their points


def _holes(invalid: np.ndarray, hole_px: int) -> np.ndarray:
    """The invalid pixels a disc of radius hole_px fits in (their opening by the disc, the
    image's edge replicated), opened only over the box of valid pixels and 2 hole_px + 2 about
    it: farther out every pixel is invalid and its own disc fits (a hand's frame, valid on a
    sixteenth of the image: 3.5 -> 0.7 ms)."""
    rows, cols = bounding_box(~invalid, 2 * hole_px + 2)
    empty = np.ones(invalid.shape, bool)
    if rows.stop == rows.start:
        return empty
    k = 2 * hole_px + 1
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    empty[rows, cols] = cv2.morphologyEx(invalid[rows, cols].astype(np.uint8), cv2.MORPH_OPEN, disc,
                                         borderType=cv2.BORDER_REPLICATE) > 0
    return empty


class FreeSpace:
    """One observation's free space as seen from its camera (camera-frame depth, world pose)."""

    def __init__(self, depth_m: np.ndarray, intrinsics: Intrinsics, T_camera_to_world: np.ndarray,
                 params: SilhouetteParams = SilhouetteParams(), beyond: np.ndarray | None = None):
        """depth_m 0 where nothing was measured; `beyond`: pixels measured past the far clip
        (their depth dropped), free space in front of them, not holes."""
        self.params, self.intrinsics = params, intrinsics
        self._pose(T_camera_to_world)
        self.depth = np.asarray(depth_m, np.float32)
        if beyond is not None:
            self.depth = np.where(beyond, np.float32(np.inf), self.depth)
        h, w = self.depth.shape
        self.empty = _holes(self.depth <= 0, params.hole_px)
        b = params.border_px
        self.judged = np.zeros((h, w), bool)
        self.judged[b:h - b, b:w - b] = True
        # Per pixel, the farthest depth of it and its right, lower and lower-right neighbours
        # (inf where one saw nothing), 0 where not judged: a point at depth z can have a
        # residual only if z + depth_margin_m is below it there (D is 0 on consistent pixels).
        far = np.where(self.empty, np.float32(np.inf), self.depth)
        block = np.maximum(np.maximum(far[:-1, :-1], far[:-1, 1:]), np.maximum(far[1:, :-1], far[1:, 1:]))
        self._reach = np.zeros((h, w), np.float32)
        self._reach[:-1, :-1] = np.where(self.judged[:-1, :-1], block, 0)
        self._reach = self._reach.reshape(-1)
        self._layers: dict[int, tuple] = {}   # layer -> (r0, r1, c0, c1, its distance transform there)
        # Per pixel the nearest depth within occluder_px, found when a search first needs it
        # (NaN until then; from the rows' minima, _rows_minima); shared with
        # moved_to's copies, as it does not depend on the pose.
        self._nearer = np.full((h, w), np.nan, np.float32)
        # Per pixel the search's last answer and its layer (-1: none yet), likewise shared: a
        # solve's iterations ask for nearly the same pixels (7-Scenes frames 1-60: 4-7 calls of
        # ~4k points an observation, ~63 ms a frame searching without it).
        self._found_layer = np.full((h, w), -1, np.int32)
        self._found = np.zeros((h, w), np.float32)
        self._ball = _ball_widths(params.occluder_px)
        self._minima, self._slot, self._box = _rows_minima(self.depth, self._ball)

    def _pose(self, T_camera_to_world: np.ndarray) -> None:
        T = np.asarray(T_camera_to_world, np.float64)
        self.R_wc, self.t_wc = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
        self.centre = T[:3, 3]

    def moved_to(self, T_camera_to_world: np.ndarray) -> FreeSpace:
        """The same observation's free space with the camera at another pose: the depth layers'
        distance transforms, the costly part, are shared (one set per observation a frame)."""
        moved = copy.copy(self)
        moved._pose(T_camera_to_world)
        return moved

    def _transform(self, layer: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Pixel distance to the nearest pixel consistent with a point at the far edge of depth
        layer `layer` (0 where consistent), over rows r0:r1 and cols c0:c1 of the image, taking
        only the pixels of that window (plus occluder_px around it) into account."""
        p = self.params
        h, w = self.depth.shape
        e = int(np.ceil(p.occluder_px / _CHAMFER_MIN)) + 2
        R0, R1, C0, C1 = max(r0 - e, 0), min(r1 + e, h), max(c0 - e, 0), min(c1 + e, w)
        depth, free = self.depth[R0:R1, C0:C1], self.empty[R0:R1, C0:C1]
        nearer = (depth > 0) & (depth < layer * p.layer_m - p.depth_margin_m)
        if nearer.any():
            # Beside a surface in front, no depth may be that surface seen edge-on.
            gap = cv2.distanceTransform((~nearer).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
            free = free & (gap > p.occluder_px)
        through = free | (depth > (layer + 1) * p.layer_m + p.depth_margin_m)
        window = through[r0 - R0:r1 - R0, c0 - C0:c1 - C0]
        return cv2.distanceTransform(window.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)

    def _distance(self, layer: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n, 4) distances of layer `layer` at the pixels (rows, cols), (rows, cols + 1),
        (rows + 1, cols), (rows + 1, cols + 1).

        The transform runs on a window around the points (a seen-through region is usually
        small next to the image) and is kept for the observation's later calls. It is exact
        where a distance is below the window's border distance (the chamfer metric's shortest
        paths stay in their bounding box, and any pixel outside is at least that far): a
        point where that fails gets the whole image's transform."""
        h, w = self.depth.shape
        box = (max(int(rows.min()) - _WINDOW_PAD_PX, 0), min(int(rows.max()) + 2 + _WINDOW_PAD_PX, h),
               max(int(cols.min()) - _WINDOW_PAD_PX, 0), min(int(cols.max()) + 2 + _WINDOW_PAD_PX, w))
        cached = self._layers.get(layer)
        if cached is None or not (cached[0] <= rows.min() and rows.max() + 2 <= cached[1]
                                  and cached[2] <= cols.min() and cols.max() + 2 <= cached[3]):
            if cached is not None:
                box = (min(box[0], cached[0]), max(box[1], cached[1]), min(box[2], cached[2]), max(box[3], cached[3]))
            cached = self._layers[layer] = (*box, self._transform(layer, *box))
        r0, r1, c0, c1, dist = cached
        a, c = rows - r0, cols - c0
        D = np.stack([dist[a, c], dist[a, c + 1], dist[a + 1, c], dist[a + 1, c + 1]], -1)
        inf = np.inf
        border = np.minimum(np.minimum(rows - r0 + 1 if r0 > 0 else inf, r1 - rows - 1 if r1 < h else inf),
                            np.minimum(cols - c0 + 1 if c0 > 0 else inf, c1 - cols - 1 if c1 < w else inf))
        if np.any(D.max(axis=1) > _CHAMFER_MIN * border):
            self._layers[layer] = (0, h, 0, w, self._transform(layer, 0, h, 0, w))
            return self._distance(layer, rows, cols)
        return D

    def _searched(self, layers: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n, 4) distances as _distance gives them, each point at its own layer, -1 for a point
        with a distance beyond search_px at one of its pixels."""
        out = np.empty((len(rows), 4), np.float32)
        p = self.params
        search(self.depth, self.empty, self._nearer, self._ball, self._minima, self._slot, self._box, rows, cols,
               layers, p.layer_m, p.depth_margin_m, p.search_px, self._found_layer, self._found, out)
        return out

    def facing(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(N,) bool: world points and normals (3, N) seen at most acos(min_view_cos) from
        face-on (either side)."""
        ray = np.asarray(points, np.float64) - self.centre[:, None]
        cos = np.einsum("ij,ij->j", ray, np.asarray(normals, np.float64))
        return np.abs(cos) >= self.params.min_view_cos * np.sqrt(np.einsum("ij,ij->j", ray, ray))

    def seen_through(self, points: np.ndarray, normals: np.ndarray, beyond_m: float = 0.0) -> np.ndarray:
        """(N,) bool: world points (N, 3) with normals the camera saw through by more than
        beyond_m (their residual)."""
        x = np.asarray(points, np.float32)
        q = x @ self.R_wc.T.astype(np.float32) + self.t_wc.astype(np.float32)
        h, w = self.depth.shape
        z = q[:, 2]
        front = z > 1e-3
        zs = np.where(front, z, 1.0)
        u = np.rint(self.intrinsics.fx * q[:, 0] / zs + self.intrinsics.cx).astype(np.int64)
        v = np.rint(self.intrinsics.fy * q[:, 1] / zs + self.intrinsics.cy).astype(np.int64)
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        cand = np.flatnonzero(inside)
        pu, pv = u[cand], v[cand]
        # Only a point whose own pixel is seen through can have a residual beyond the margin.
        through = self.judged[pv, pu] & (self.empty[pv, pu] | (self.depth[pv, pu] > z[cand] + self.params.depth_margin_m))
        cand = cand[through]
        out = np.zeros(len(x), bool)
        if len(cand):
            pts = _components(x[cand])
            out[cand] = (self.residuals(pts)[0] > beyond_m) & self.facing(pts, _components(normals[cand]))
        return out

    def residuals(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) residuals r >= 0 (metres) of world points (3, N) given as components, and their
        gradients dr/dx (3, N) in world coordinates (zero where r = 0)."""
        p = self.params
        intr = self.intrinsics
        x = np.ascontiguousarray(points, np.float64)
        n = x.shape[1]
        r, grad = np.zeros(n), np.zeros((3, n))
        h, w = self.depth.shape
        # The few points that can be seen through, found in one compiled pass (numpy's passes
        # over every point took ~4 of a call's 6 ms on tube-wall's 120k, five calls a frame).
        sel, uv, q = np.empty(n, np.int64), np.empty((2, n)), np.empty((3, n))
        k = within_reach(x, np.ascontiguousarray(self.R_wc, np.float64), np.ascontiguousarray(self.t_wc, np.float64),
                         intr.fx, intr.fy, intr.cx, intr.cy, h, w, self._reach, p.depth_margin_m, sel, uv, q)
        sel, (u, v), q = sel[:k], uv[:, :k], q[:, :k]
        ui, vi = u.astype(np.int64), v.astype(np.int64)        # floor: u, v >= 0
        z = q[2]
        layer = np.floor(z / p.layer_m).astype(np.int64)
        D = np.full((len(sel), 4), -1.0)
        if p.search_px > 0 and len(sel):
            D[:] = self._searched(layer, vi, ui)
        far = np.flatnonzero((D < 0).any(axis=1))
        for k in np.unique(layer[far]):
            m = far[layer[far] == k]
            D[m] = self._distance(int(k), vi[m], ui[m])
        fu, fv = u - ui, v - vi
        d = (1 - fu) * (1 - fv) * D[:, 0] + fu * (1 - fv) * D[:, 1] + (1 - fu) * fv * D[:, 2] + fu * fv * D[:, 3]
        out = d > p.margin_px
        sel, d, fu, fv, D, q = sel[out], d[out], fu[out], fv[out], D[out], q[:, out]
        dd_du = (1 - fv) * (D[:, 1] - D[:, 0]) + fv * (D[:, 3] - D[:, 2])
        dd_dv = (1 - fu) * (D[:, 2] - D[:, 0]) + fu * (D[:, 3] - D[:, 1])
        X, Y, Z = q
        f = intr.fx
        r[sel] = Z * (d - p.margin_px) / f
        # r = Z (D(u, v) - margin) / f, u = fx X / Z + cx, v = fy Y / Z + cy: camera-frame gradient.
        gq = np.stack([dd_du * intr.fx / f,
                       dd_dv * intr.fy / f,
                       (d - p.margin_px) / f - (dd_du * intr.fx * X + dd_dv * intr.fy * Y) / (Z * f)])
        grad[:, sel] = self.R_wc.T @ gq
        return r, grad



def _components(points: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(points, np.float64).T)


def _rows_minima(depth: np.ndarray, ball: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observation's nearest depths within the ball, prepared when it is built (on the
    run's read-ahead worker): each row's minima at the ball's half-widths (row_minima) over the
    measured rows and the columns within the ball of them, from which a search's nearest depth
    takes 2 r + 1 reads instead of the ball's ~1.8k (a touch frame's first search 2.2 ms, a
    sheet's 4.8; 7-Scenes frames 1-60 ~14 ms a frame, where the minima take 4.6 ms on the
    worker). (minima, slot of each half-width, box r0, r1, c0, c1); an empty box if nothing is
    measured."""
    reach = int(ball.max())
    slot = np.full(reach + 1, -1, np.int64)
    widths = np.unique(ball)
    slot[widths] = np.arange(len(widths))
    rows, cols = bounding_box(depth > 0, 0)
    if rows.stop == rows.start:
        return np.zeros((len(widths), 0, 0), np.float32), slot, np.zeros(4, np.int64)
    r0, r1, c0, c1 = rows.start, rows.stop, max(cols.start - reach, 0), min(cols.stop + reach, depth.shape[1])
    return row_minima(depth, slot, r0, r1, c0, c1), slot, np.array([r0, r1, c0, c1], np.int64)


@functools.lru_cache(maxsize=4)
def _ball_widths(radius_px: int) -> np.ndarray:
    """Half-widths of the rows dy = -radius..radius of the pixels within chamfer distance
    radius_px of a pixel (the ball the occluder test's transform looks into). Made once: ~1k
    calls into a compiled function, 1.4 ms a touch frame when made with each observation."""
    r = int(radius_px)
    out = np.array([max(dx for dx in range(r + 1) if chamfer(dy, dx) <= r) for dy in range(-r, r + 1)], np.int64)
    out.flags.writeable = False
    return out
