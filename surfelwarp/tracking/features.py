"""Colour correspondences between two images, lifted to 3-D and cleaned of outliers.

Depth cannot see motion along a surface (SurfelWarp Fig. 9b); colour can. Features (SIFT by
default, ORB as the fast option) are detected where there is depth and matched by descriptor
with Lowe's ratio test and a mutual check; dense optical flow (DIS) gives pairs on a grid where
a surface has too little texture for features (flow.py). Each pair's end is refined to
sub-pixel by aligning its patch (patch_align.py). Pairs are lifted to 3-D with each frame's
vertex map (sub-pixel) and kept only near their predicted position (max_motion_m, and a few
times the median distance from it) and where they agree with their neighbours: a pair whose
distances to the nearby pairs change by more than a small tolerance breaks local rigidity
(rigidity.py). colour.py puts the survivors on the model; terms/features.py puts them in the
solve.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.geometry.se3 import transform_points
from surfelwarp.tracking.descriptors import nearest_both_ways
from surfelwarp.tracking.patch_align import ALIGNED, FAILED, PLAIN, MotionPrior, align
from surfelwarp.tracking.rigidity import locally_rigid


DETECTORS = ("sift", "orb")


@dataclass(frozen=True)
class FeatureParams:
    detector: str = "sift"
    max_features: int = 2000
    sift_contrast: float = 0.04         # SIFT's contrast threshold (OpenCV's default)
    ratio: float = 0.8                  # Lowe's test: best distance below this share of the second
    max_motion_m: float = 0.3           # a feature moving farther between two frames is an outlier,
    motion_spread: float = 3.0          # and one farther than this times the median distance from
    motion_floor_m: float = 0.02        # the prediction (at least this) of its motion_neighbours
    motion_neighbours: int = 16         # nearest pairs
    rigidity_radius_m: float = 0.06     # neighbours whose distance is compared
    rigidity_tolerance: float = 0.1     # a distance may change by this share of itself ...
    rigidity_floor_m: float = 0.006     # ... or by this much (depth noise, pixel rounding)
    min_agreement: float = 0.6          # share of a match's neighbours whose distances agree
    min_neighbours: int = 2             # a match with fewer neighbours has no support: dropped
    anchor_distance_m: float = 0.01     # a feature is put on the model surfel drawn at its pixel
                                        # if that surfel is this close to the feature's depth point
    flow: bool = True                   # dense optical flow too (from the model's colour, colour.py)
    flow_stride_px: int = 8             # its grid
    flow_shift_px: float = 8.0          # the last frame's features moving farther than this (median)
                                        # start the flow's search there (0: never)
    flow_weight: float = 1.0            # a flow pair's weight against a feature's (the shirt pair:
                                        # EPE 38 mm at 0.3, 25 mm at 1)
    refine_radius_px: int = 6           # each pair aligned on a patch of 2r+1 pixels (0: not refined)
    refine_max_px: float = 2.0          # a pair whose patch matches nothing this close is dropped
    refine_depth_m: float = 0.03        # the patch pixels within this depth of its centre's count

    CHOICES = {"detector": DETECTORS}
    ZERO_OK = {"sift_contrast", "motion_floor_m", "rigidity_tolerance", "rigidity_floor_m", "min_agreement",
               "min_neighbours", "flow_weight", "refine_radius_px", "flow_shift_px"}
    UNIT = {"ratio", "min_agreement"}
    AT_MOST = {"flow_stride_px": 256, "refine_radius_px": 31}


@dataclass(frozen=True)
class Keypoints:
    """One frame's features: pixel positions (n, 2) (x, y), descriptors and the grey image
    they were found in."""
    pixels: np.ndarray
    descriptors: np.ndarray | None
    image: np.ndarray | None = None


@dataclass(frozen=True)
class FeatureMatches:
    """Matched features of a previous and a current frame: pixels (n, 2) (x, y) and points
    (n, 3) in each frame's camera."""
    previous_pixels: np.ndarray
    current_pixels: np.ndarray
    previous_points: np.ndarray
    current_points: np.ndarray

    def __len__(self) -> int:
        return len(self.previous_points)

    def select(self, keep: np.ndarray) -> "FeatureMatches":
        return FeatureMatches(self.previous_pixels[keep], self.current_pixels[keep], self.previous_points[keep],
                              self.current_points[keep])


def grey(color: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(color, np.uint8), cv2.COLOR_RGB2GRAY)


def bounding_box(mask: np.ndarray, margin_px: int = 16) -> tuple[slice, slice]:
    """Rows and columns around the True pixels (plus a margin): features and flow are computed on
    that window only, whose area, not the image's, sets their cost (two fingers fill a tenth)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return slice(0, 0), slice(0, 0)
    h, w = mask.shape
    return (slice(max(rows[0] - margin_px, 0), min(rows[-1] + margin_px + 1, h)),
            slice(max(cols[0] - margin_px, 0), min(cols[-1] + margin_px + 1, w)))


def detect(color: np.ndarray, valid: np.ndarray, params: FeatureParams) -> Keypoints:
    """Features of an RGB image where `valid` (depth) holds, away from its edges (a feature on
    a depth edge mixes foreground and background)."""
    mask = cv2.erode(np.asarray(valid, np.uint8), np.ones((5, 5), np.uint8))
    rows, cols = bounding_box(mask)
    image = grey(color)
    if rows.stop - rows.start < 16 or cols.stop - cols.start < 16:
        return Keypoints(np.zeros((0, 2), np.float32), None, image)
    if params.detector == "sift":
        detector = cv2.SIFT_create(nfeatures=params.max_features, contrastThreshold=params.sift_contrast)
    else:
        detector = cv2.ORB_create(nfeatures=params.max_features)
    kp, desc = detector.detectAndCompute(np.ascontiguousarray(image[rows, cols]),
                                         np.ascontiguousarray(mask[rows, cols]))
    pixels = np.array([k.pt for k in kp], np.float32).reshape(-1, 2) + [cols.start, rows.start]
    return Keypoints(pixels.astype(np.float32), desc, image)


def surface_depth(vertex_map: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(H, W) depth in metres where `valid`, 0 elsewhere: the depth `refine` reads."""
    return where_image(valid, vertex_map[..., 2], np.zeros((), np.asarray(vertex_map).dtype))


def where_image(mask: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.where(mask, a, b) for (H, W) masks over images (H, W) or (H, W, C), b broadcast if it
    is not one: b copied, then a over it where mask (cv2.copyTo). The same values; numpy's
    broadcast select took 3.5 ms on a 640x480 colour image, this 0.05."""
    dtype = np.result_type(a, b)
    if dtype not in _CV_COPIES or np.ndim(a) not in (2, 3) or np.ndim(a) == 3 and np.shape(a)[2] > 4:
        return np.where(mask if np.ndim(a) == 2 else np.asarray(mask)[..., None], a, b)
    out = np.empty(np.shape(a), dtype)
    out[...] = b
    cv2.copyTo(np.ascontiguousarray(a, dtype), np.ascontiguousarray(mask, np.uint8), out)
    return out


# What cv2.copyTo copies (other dtypes and more than 4 channels go to numpy).
_CV_COPIES = {np.dtype(t) for t in (np.uint8, np.int8, np.uint16, np.int16, np.int32, np.float32, np.float64)}


def refine(previous_grey: np.ndarray | None, current_grey: np.ndarray | None, pa: np.ndarray, pb: np.ndarray,
           params: FeatureParams, previous_depth: np.ndarray | None = None, prior: MotionPrior | None = None
           ) -> tuple[np.ndarray, np.ndarray]:
    """(pb moved to where pa's patch of the previous image lies in the current one, whether to
    keep the pair): patch_align.align on the patch pixels of pa's surface (`previous_depth`,
    metres, 0: none), each moved first as `prior` predicts (patch_align.MotionPrior). A pair
    whose textured patch matches nothing within refine_max_px of pb is wrong and dropped
    (keeping those lost the track of `fast`, EPE 0.9 -> 10.9 mm); one whose patch cannot say is
    kept at a depth edge as found; a plain one is moved by the correction of the aligned pairs
    on its surface around it, or dropped without them (neighbours_correction)."""
    if params.refine_radius_px == 0 or len(pa) == 0 or previous_grey is None or current_grey is None:
        return pb, np.ones(len(pa), bool)
    moved, status = align(previous_grey, current_grey, pa, pb, params.refine_radius_px, previous_depth,
                          params.refine_depth_m, params.refine_max_px, prior=prior)
    plain, aligned = np.flatnonzero(status == PLAIN), np.flatnonzero(status == ALIGNED)
    depth = None if previous_depth is None else pixel_values(pa, previous_depth)
    correction, vouched = neighbours_correction(pa[plain], pa[aligned], moved[aligned] - pb[aligned],
                                                None if depth is None else (depth[plain], depth[aligned]),
                                                params.refine_depth_m)
    moved[plain] += correction
    keep = status != FAILED
    keep[plain[~vouched]] = False
    return moved.astype(np.float32), keep


CORRECTED_BY = 8            # a plain patch's pair takes the median correction of up to this many
CORRECTION_REACH_PX = 24.0  # aligned pairs on its surface within this distance (three steps of the
CORRECTION_MIN = 3          # flow's grid), and is dropped with fewer of them


def neighbours_correction(points: np.ndarray, aligned: np.ndarray, correction: np.ndarray,
                          depths: tuple[np.ndarray, np.ndarray] | None = None, depth_tol_m: float = 0.03
                          ) -> tuple[np.ndarray, np.ndarray]:
    """((n, 2) the median `correction` (the refinement's move of each `aligned` pair, from where
    it was found) of the aligned pairs nearest each of `points`, and whether CORRECTION_MIN of
    them lie within CORRECTION_REACH_PX (elsewhere the correction is 0)). `depths` (of points,
    of aligned; metres, 0: none) keeps the neighbours to those within depth_tol_m of a point's
    surface. DIS's flow falls short of the motion, and a lamp's shading moves it, the same way
    over a neighbourhood; a plain patch cannot be aligned itself, so it takes what its aligned
    neighbours needed: against keeping its pair as found, `touch` over five seeds 0.634 ->
    0.606 mm, `orbit` 0.54 -> 0.53. Without them on its own surface, its flow is what DIS
    carried over from the textured surfaces around, whatever their motion, and refine drops it:
    `limb-plainwall`'s plain wall moved with the textured limb before it (mean EPE 128.9 mm;
    0.25 with the colour pose's cover test, tracker.py; depth alone 0.85). Dropping every plain
    pair instead cost `release` over ten seeds 1.095 -> 1.188."""
    out, vouched = np.zeros((len(points), 2)), np.zeros(len(points), bool)
    if len(points) == 0 or len(aligned) < CORRECTION_MIN:
        return out, vouched
    k = min(CORRECTED_BY, len(aligned))
    d, nb = KDTree(np.ascontiguousarray(aligned, np.float64)).query(np.ascontiguousarray(points, np.float64), k=k,
                                                                   distance_upper_bound=CORRECTION_REACH_PX)
    d, nb = d.reshape(len(points), k), nb.reshape(len(points), k)
    nb = np.minimum(nb, len(aligned) - 1)
    near = np.isfinite(d)
    if depths is not None:
        z, z_aligned = (np.asarray(a, np.float64) for a in depths)
        near &= (z[:, None] > 0) & (np.abs(z_aligned[nb] - z[:, None]) < depth_tol_m)
    values = np.where(near[..., None], np.asarray(correction, np.float64)[nb], np.nan)
    vouched = near.sum(1) >= CORRECTION_MIN
    out[vouched] = np.nanmedian(values[vouched], axis=1)
    return out, vouched


def match_descriptors(a: Keypoints, b: Keypoints, params: FeatureParams) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) that pass the ratio test both ways and pick each other."""
    if a.descriptors is None or b.descriptors is None or len(a.pixels) < 2 or len(b.pixels) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if params.detector == "sift":
        ab, ba = nearest_both_ways(a.descriptors, b.descriptors, params.ratio)
    else:   # ORB's binary descriptors: brute force Hamming
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

        def best(x, y):
            pairs = matcher.knnMatch(x, y, k=2)
            idx = np.array([m[0].trainIdx if len(m) == 2 else -1 for m in pairs], np.int64)
            d = np.array([(m[0].distance, m[1].distance) if len(m) == 2 else (1.0, 1.0) for m in pairs], np.float64)
            return np.where((idx >= 0) & (d[:, 0] < params.ratio * d[:, 1]), idx, -1)

        ab, ba = best(a.descriptors, b.descriptors), best(b.descriptors, a.descriptors)
    ia = np.flatnonzero(ab >= 0)
    ib = ab[ia]
    mutual = ba[ib] == ia
    return ia[mutual], ib[mutual]


def lift(pixels: np.ndarray, vertex_map: np.ndarray, valid: np.ndarray,
         edge_m: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Camera points at sub-pixel positions (x, y), and whether the nearest pixel has depth: the
    vertex map interpolated bilinearly where the four pixels around have depth within edge_m of
    each other, else the nearest pixel's (rounding alone is off by up to half a pixel, ~1 mm at
    1 m, as much as the depth noise a feature is meant to see past)."""
    h, w = valid.shape
    x = np.clip(np.asarray(pixels[:, 0], np.float64), 0, w - 1.0001)
    y = np.clip(np.asarray(pixels[:, 1], np.float64), 0, h - 1.0001)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    v = vertex_map      # the four corners gathered, then widened (not the whole map)
    corners = [v[y0, x0].astype(np.float64), v[y0, x0 + 1].astype(np.float64), v[y0 + 1, x0].astype(np.float64),
               v[y0 + 1, x0 + 1].astype(np.float64)]
    z = np.stack([c[:, 2] for c in corners], -1)
    smooth = valid[y0, x0] & valid[y0, x0 + 1] & valid[y0 + 1, x0] & valid[y0 + 1, x0 + 1] & \
        (z.max(axis=1) - z.min(axis=1) < edge_m)
    bilinear = (corners[0] * (1 - fx) + corners[1] * fx) * (1 - fy) + (corners[2] * (1 - fx) + corners[3] * fx) * fy
    nearest = pixel_values(pixels, vertex_map).astype(np.float64)
    return np.where(smooth[:, None], bilinear, nearest), pixel_values(pixels, valid)


def match_frames(previous: Keypoints, current: Keypoints, previous_vertex: np.ndarray, previous_valid: np.ndarray,
                 current_vertex: np.ndarray, current_valid: np.ndarray, T_previous_to_current: np.ndarray,
                 params: FeatureParams) -> FeatureMatches:
    """Descriptor matches, checked in 3-D (checked_pairs)."""
    ia, ib = match_descriptors(previous, current, params)
    pb, keep = refine(previous.image, current.image, previous.pixels[ia], current.pixels[ib], params,
                      surface_depth(previous_vertex, previous_valid))
    pa, pb = previous.pixels[ia][keep], pb[keep]
    return checked_pairs(pa, pb, previous_vertex, previous_valid, current_vertex, current_valid,
                         T_previous_to_current, params)


def checked_pairs(pa: np.ndarray, pb: np.ndarray, previous_vertex: np.ndarray, previous_valid: np.ndarray,
                  current_vertex: np.ndarray, current_valid: np.ndarray, T_previous_to_current: np.ndarray,
                  params: FeatureParams) -> FeatureMatches:
    """Pixel pairs lifted to 3-D with depth at both ends (checked_points)."""
    qa, ok_a = lift(pa, previous_vertex, previous_valid)
    return checked_points(pa, pb, qa, ok_a, current_vertex, current_valid, T_previous_to_current, params)


def near_prediction(deviation: np.ndarray, candidate: np.ndarray, params: FeatureParams,
                    points: np.ndarray | None = None) -> np.ndarray:
    """Pairs whose distance from the predicted position is below max_motion_m and below
    motion_spread times the median of the candidates near them (at least motion_floor_m): a
    group of wrong pairs that agree among themselves passes the local rigidity test, not this
    one, unless the pairs around it moved that far too (the shirt pair: every pair ~20 cm from
    the prediction; a ball rolling 5 cm between frames in a still room: the pairs on the ball).
    `points` (n, 3) place the pairs; the median is over each one's motion_neighbours nearest
    candidates, or over all candidates without points."""
    ok = np.zeros(len(deviation), bool)
    idx = np.flatnonzero(candidate)
    if len(idx) == 0:
        return ok
    if points is None or len(idx) <= params.motion_neighbours:
        typical = np.full(len(idx), np.median(deviation[idx]))
    else:
        c = np.ascontiguousarray(points[idx], np.float64)
        _, near = KDTree(c).query(c, k=params.motion_neighbours)
        typical = np.median(deviation[idx][near.reshape(len(c), -1)], axis=1)
    bound = np.minimum(params.max_motion_m, np.maximum(params.motion_floor_m, params.motion_spread * typical))
    ok[idx] = deviation[idx] < bound
    return ok


def checked_points(pa: np.ndarray, pb: np.ndarray, qa: np.ndarray, ok_a: np.ndarray, current_vertex: np.ndarray,
                   current_valid: np.ndarray, T_previous_to_current: np.ndarray, params: FeatureParams
                   ) -> FeatureMatches:
    """Previous points qa (camera) seen at pa paired with the current depth at pb, then the
    motion bound (in the current camera, the previous points moved by the camera's motion) and
    local rigidity."""
    qb, ok_b = lift(pb, current_vertex, current_valid)
    ok = ok_a & ok_b
    qa_now = transform_points(T_previous_to_current, qa)
    ok &= near_prediction(np.linalg.norm(qb - qa_now, axis=1), ok, params, qa_now)
    matches = FeatureMatches(pa[ok], pb[ok], qa[ok], qb[ok])
    if len(matches) == 0:
        return matches
    return matches.select(locally_rigid(qa_now[ok], qb[ok], params))


@dataclass(frozen=True)
class ModelView:
    """The model as the feature stage reads it: `index_map` (H, W) of the surfels drawn at the
    last pose (-1: none), the solved surfels `visible` (sorted), and every surfel's live
    position (world), unique id (ascending; None: points do not live on), skinning knn and
    weights; optionally the drawn points (camera frame at the last pose), the fused colour
    (uint8 RGB) where `color_drawn`, interpolated about the surfels' centres
    (render.colour_map), every surfel's reference position (world) and the drawn normals (camera
    frame at the last pose)."""
    index_map: np.ndarray
    visible: np.ndarray
    live_position: np.ndarray
    ids: np.ndarray | None
    knn: np.ndarray
    weights: np.ndarray
    vertex_map: np.ndarray | None = None
    color_map: np.ndarray | None = None
    color_drawn: np.ndarray | None = None
    ref_position: np.ndarray | None = None
    normal_map: np.ndarray | None = None


@dataclass(frozen=True)
class Keyframe:
    """The reference frame's features with the world point and the surfel (by id) each lies on."""
    keypoints: Keypoints
    points: np.ndarray          # (n, 3) world, reference frame
    ids: np.ndarray             # (n,) surfel ids
    depth: np.ndarray | None = None   # (H, W) the reference frame's depth (0: none)


@dataclass(frozen=True)
class AnchoredMatches:
    """Matches put on the model: the solved surfel each feature lies on, the feature's
    reference-frame point (world) and where the current frame sees it (current camera)."""
    index: np.ndarray           # (n,) into the solved surfels
    ref_points: np.ndarray      # (n, 3)
    target_points: np.ndarray   # (n, 3)
    weights: np.ndarray         # (n,) each match's weight against a feature's

    def __len__(self) -> int:
        return len(self.index)


def combine(*sets: AnchoredMatches) -> AnchoredMatches:
    """The sets' matches, one a surfel (the first set's first): the feature term reads a
    feature's reference point in its surfel's place. No sets: no matches."""
    if not sets:
        return AnchoredMatches(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    index = np.concatenate([m.index for m in sets])
    first = np.unique(index, return_index=True)[1]
    return AnchoredMatches(index[first], np.concatenate([m.ref_points for m in sets])[first],
                           np.concatenate([m.target_points for m in sets])[first],
                           np.concatenate([m.weights for m in sets])[first])


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The (H, W) image at points (x, y), interpolated bilinearly (clamped to the image)."""
    h, w = image.shape
    x, y = np.clip(x, 0.0, w - 1.0), np.clip(y, 0.0, h - 1.0)
    x0, y0 = np.minimum(x.astype(np.int64), w - 2), np.minimum(y.astype(np.int64), h - 2)
    fx, fy = x - x0, y - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    return top * (1 - fy) + (image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx) * fy


def pixel_values(pixels: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The image's values at the pixel centres nearest to (x, y) positions."""
    h, w = image.shape[:2]
    col = np.clip(np.rint(pixels[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.rint(pixels[:, 1]).astype(np.int64), 0, h - 1)
    return image[row, col]


def solved_index(index: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of model indices among the sorted solved surfels, and whether each is one."""
    if len(visible) == 0:
        return np.zeros(len(index), np.int64), np.zeros(len(index), bool)
    pos = np.minimum(np.searchsorted(visible, index), len(visible) - 1)
    return pos, (visible[pos] == index) & (index >= 0)
