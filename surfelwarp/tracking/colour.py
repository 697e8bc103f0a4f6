"""The tracker's colour correspondences: features and dense flow, put on the model.

Each frame's SIFT (or ORB) features are matched with the reference frame's (drift-free while
they still match; new with every reference) and the last frame's, and dense optical flow runs
from the model's fused colour drawn at the last pose into the frame; every pair is lifted to 3-D
with depth and checked (features.py), then put on a surfel the solve uses with its reference
point. terms/features.py adds them to the non-rigid solve.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.deform.warp_field import WarpField, inverse_warp, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, transform_points
from surfelwarp.preprocess import CameraObservation
from surfelwarp.tracking.ahead import FoundAhead
from surfelwarp.tracking.features import (AnchoredMatches, FeatureMatches, FeatureParams, Keyframe, Keypoints,
                                          ModelView, checked_pairs, checked_points, combine, detect, lift,
                                          match_descriptors, match_frames, near_prediction, pixel_values, refine,
                                          solved_index, surface_depth, where_image)
from surfelwarp.tracking.flow import flow_at, flow_pairs, grid_pixels
from surfelwarp.tracking.patch_align import MotionPrior
from surfelwarp.tracking.relight import Relight
from surfelwarp.tracking.rigidity import locally_rigid


@dataclass(frozen=True)
class KeyframePairs:
    """Reference features seen in the current frame: their index in the keyframe and their
    point (current camera)."""
    index: np.ndarray           # (n,) into the keyframe's features
    points: np.ndarray          # (n, 3)


def common_shift(matches: FeatureMatches, min_px: float, min_matches: int = 8) -> np.ndarray | None:
    """The matches' median image motion (x, y), if at least min_matches move it farther than
    min_px (else None)."""
    if min_px <= 0 or len(matches) < min_matches:
        return None
    shift = np.median(matches.current_pixels - matches.previous_pixels, axis=0)
    return shift if np.hypot(*shift) > min_px else None


def keyframe_pairs(keyframe: Keyframe, current: Keypoints, current_vertex: np.ndarray, current_valid: np.ndarray,
                   params: FeatureParams) -> KeyframePairs:
    """The reference features found in the current frame: descriptor matches, refined, lifted
    with the current depth (`_keyframe_matches` checks them against the warp)."""
    ia, ib = match_descriptors(keyframe.keypoints, current, params)
    pixels, keep = refine(keyframe.keypoints.image, current.image, keyframe.keypoints.pixels[ia], current.pixels[ib],
                          params, keyframe.depth)
    ia, pixels = ia[keep], pixels[keep]
    points, ok = lift(pixels, current_vertex, current_valid)
    return KeyframePairs(ia[ok], points[ok])


@dataclass(frozen=True)
class EarlyColour:
    """What `ColourMatcher.ahead` found for an observation before its frame: its features, its
    matches with the observation before it (`last`) and with the keyframe it saw."""
    keypoints: Keypoints
    last: CameraObservation | None
    last_matches: FeatureMatches | None
    keyframe: Keyframe | None
    keyframe_pairs: KeyframePairs | None


class ColourMatcher:
    """Colour correspondences from frame to frame; holds the reference frame's features, the
    last observation's and, during `matches`, the frame's poses."""

    def __init__(self, intrinsics: Intrinsics, params: FeatureParams = FeatureParams()):
        self.intrinsics, self.params = intrinsics, params
        self._previous_features: tuple[Keypoints, CameraObservation] | None = None
        self._detected: tuple[CameraObservation, Keypoints] | None = None
        self._keyframe: Keyframe | None = None
        self._T_last = np.eye(4)
        self._ahead_last: tuple[Keypoints, CameraObservation] | None = None   # the read-ahead worker's
        self._found = FoundAhead()                  # EarlyColour by observation

    def __getstate__(self) -> dict:
        """A checkpoint's copy (io/checkpoint.py) leaves out what was found ahead: the resumed
        run finds it again."""
        return self.__dict__ | {"_ahead_last": None}

    def _keypoints(self, obs: CameraObservation) -> Keypoints:
        """The observation's features, detected once."""
        if self._detected is None or self._detected[0] is not obs:
            early = self._found.get(obs)
            self._detected = obs, early.keypoints if early is not None else detect(obs.color, obs.valid, self.params)
        return self._detected[1]

    def ahead(self, obs: CameraObservation) -> None:
        """The colour work on `obs` that reads no model, done before its frame: its features,
        its matches with the observation given to `ahead` before it and with the keyframe. The
        run calls it on its read-ahead worker while the frame before is processed; `matches`
        takes what it found where the last observation and the keyframe are the ones it saw
        (after a skipped frame or a new reference it finds them again), the same bytes as
        finding them then."""
        if obs.color is None:
            self._ahead_last = None
            return
        p, last, keyframe = self.params, self._ahead_last, self._keyframe   # the keyframe read once
        kp = detect(obs.color, obs.valid, p)
        last_matches = pairs = None
        if last is not None:
            last_kp, last_obs = last
            last_matches = match_frames(last_kp, kp, last_obs.vertex_map, last_obs.valid, obs.vertex_map, obs.valid,
                                        np.eye(4), p)
        if keyframe is not None:
            pairs = keyframe_pairs(keyframe, kp, obs.vertex_map, obs.valid, p)
        self._ahead_last = kp, obs
        self._found.put(obs, EarlyColour(kp, None if last is None else last[1], last_matches, keyframe, pairs))

    def new_reference(self, obs: CameraObservation, T_camera_to_world: np.ndarray, ids: np.ndarray,
                      ref_position: np.ndarray) -> None:
        """Keep the reference frame's features, each on the reference surfel (world) at its
        depth point: matched into every later frame, they stop frame-to-frame drift adding up.
        Call with each new reference (the first frame, every reinitialisation)."""
        self._keyframe = None
        if obs.color is None or len(ref_position) == 0:
            return
        kp = self._keypoints(obs)
        q, ok = lift(kp.pixels, obs.vertex_map, obs.valid)
        world = transform_points(T_camera_to_world, q[ok])
        if len(world) == 0 or kp.descriptors is None:
            return
        d, j = KDTree(np.asarray(ref_position, np.float64)).query(world)
        near = d < self.params.anchor_distance_m
        self._keyframe = Keyframe(Keypoints(kp.pixels[ok][near], kp.descriptors[ok][near], kp.image), world[near],
                                  np.asarray(ids)[j[near]], surface_depth(obs.vertex_map, obs.valid))

    def matches(self, obs: CameraObservation, model: ModelView | None, field: WarpField | None,
                T_last: np.ndarray, T_predicted: np.ndarray | None = None,
                ended: WarpField | None = None) -> AnchoredMatches | None:
        """Colour correspondences of `obs` with the reference frame's and the last frame's, on
        the surfels the solve uses (`field`: the warp the frame starts from, as `model` is
        drawn; `ended`: the one the last frame ended with, if its nodes were carried on since
        (prediction.py); T_last the last frame's camera-to-world pose, the prediction of this
        one's: the checks allow the camera's motion as they allow the scene's; T_predicted, its
        pose predicted by the camera's last motion, primes the flow's patch alignment).
        Remembers obs for the next frame; with no model (the first frame) that is all. None
        without colour."""
        if obs.color is None:
            self._previous_features = None
            return None
        self._T_last = T_last
        p = self.params
        early = self._found.get(obs)
        kp = self._keypoints(obs)
        previous, self._previous_features = self._previous_features, (kp, obs)
        if model is None:
            return None
        found = []
        if self._keyframe is not None:
            pairs = early.keyframe_pairs if early is not None and early.keyframe is self._keyframe else None
            found.append(self._keyframe_matches(kp, obs, model, field, pairs))
        if previous is not None:
            last_kp, last = previous
            T = np.eye(4)         # last to this camera, predicted (as `ahead` predicts it)
            if early is not None and early.last is last:
                last_matches = early.last_matches
            else:
                last_matches = match_frames(last_kp, kp, last.vertex_map, last.valid, obs.vertex_map, obs.valid, T, p)
            found.append(self._on_model(last_matches, model, field, 1.0, ended))
            if p.flow:
                found.append(self._flow_matches(last, last_kp.image, obs, model, field, T,
                                                self._prior(T_last, T_predicted),
                                                common_shift(last_matches, p.flow_shift_px), ended))
        if not found:
            return None
        return combine(*found)

    def _prior(self, T_last: np.ndarray, T_predicted: np.ndarray | None) -> MotionPrior | None:
        """The camera's predicted motion from the last pose, which the flow's patches follow first
        (patch_align.MotionPrior); None without a prediction."""
        return None if T_predicted is None else MotionPrior(self.intrinsics, invert(T_predicted) @ T_last)

    def _keyframe_matches(self, kp: Keypoints, obs: CameraObservation, model: ModelView,
                          field: WarpField, pairs: KeyframePairs | None) -> AnchoredMatches:
        """Reference features in `obs` (`pairs`, found ahead; None: found now), checked against
        where the last frame's warp takes them."""
        p, kf = self.params, self._keyframe
        if len(model.ids) == 0:
            return combine()
        if pairs is None:
            pairs = keyframe_pairs(kf, kp, obs.vertex_map, obs.valid, p)
        ia, q = pairs.index, pairs.points
        index = np.minimum(np.searchsorted(model.ids, kf.ids[ia]), len(model.ids) - 1)
        ok = model.ids[index] == kf.ids[ia]          # surfels removed since are gone
        ia, q, index = ia[ok], q[ok], index[ok]
        predicted, _ = warp(kf.points[ia], None, model.knn[index], model.weights[index], field)
        # The solve's surfels are those the model map shows, one a pixel: the feature goes on
        # the one drawn where the last frame's warp puts it (its neighbour, skinned alike).
        pixels = self.intrinsics.project(transform_points(invert(self._T_last), predicted))
        drawn, ok = on_model_map(pixels, predicted, model, p.anchor_distance_m)
        solved, in_solve = solved_index(drawn, model.visible)
        seen = transform_points(self._T_last, q)
        ok &= in_solve
        ok &= near_prediction(np.linalg.norm(predicted - seen, axis=1), ok, p, predicted)
        keep = np.flatnonzero(ok)[locally_rigid(predicted[ok], seen[ok], p)]
        return AnchoredMatches(solved[keep], kf.points[ia[keep]], q[keep], np.ones(len(keep)))

    def _flow_matches(self, last: CameraObservation, last_grey: np.ndarray, obs: CameraObservation,
                      model: ModelView, field: WarpField, T_last_to_now: np.ndarray, prior: MotionPrior | None = None,
                      shift_px: np.ndarray | None = None, ended: WarpField | None = None) -> AnchoredMatches:
        """Dense flow into `obs` from the model's fused colour drawn at the last pose: the flow
        finds where the model's own texture went, so frame-to-frame errors do not add up as
        they do with flow from the last frame (used where the model has no colour drawn; its
        pairs start where the last frame saw them, `ended`'s surface, _on_model). `last_grey`:
        the last frame's grey image (its features' Keypoints.image), which relights the model's."""
        p = self.params
        current = (obs.vertex_map, obs.valid, T_last_to_now, p)
        if model.color_map is None or model.vertex_map is None or not model.color_drawn.any():
            pairs = flow_pairs(last.color, obs.color, last.valid, obs.valid, p,
                               surface_depth(last.vertex_map, last.valid), prior)
            return self._on_model(checked_pairs(*pairs, last.vertex_map, last.valid, *current), model, field,
                                  p.flow_weight, ended)
        # The model's colour is drawn interpolated about the surfels' centres (render.colour_map),
        # so each grid pixel's pair starts where the centre of the surfel drawn there projects.
        drawn = model.color_drawn
        source = where_image(drawn, model.color_map, last.color)
        grid = grid_pixels(drawn, p.flow_stride_px).astype(np.int64)
        centres = model.vertex_map[grid[:, 1], grid[:, 0]].astype(np.float64)
        pa = self.intrinsics.project(centres).astype(np.float32)
        depth = where_image(drawn, model.vertex_map[..., 2], surface_depth(last.vertex_map, last.valid))
        relight = None if model.normal_map is None else Relight(model.normal_map, drawn, obs.valid, last_grey,
                                                                 last.valid)
        pb, inside = flow_at(source, obs.color, drawn | obs.valid, pa, p, depth, prior, shift_px, relight)
        m = checked_points(pa[inside], pb[inside], centres[inside], np.ones(int(inside.sum()), bool), *current)
        return self._on_model(m, model, field, p.flow_weight)

    def _on_model(self, m: FeatureMatches, model: ModelView, field: WarpField, weight: float,
                  ended: WarpField | None = None) -> AnchoredMatches:
        """Last-frame matches on the surfels the model map showed at them, taken back to the
        reference by `field`, or, where the nodes were carried on since the last frame ended
        (`ended`, prediction.py), by the field it ended with: the last frame's points lie on
        the surface as that field put it (by `field`, a point on a node carried 4 cm would be
        taken back 4 cm short, and its pair would pull the node on by twice its motion)."""
        world = transform_points(self._T_last, m.previous_points)
        at = field if ended is None else ended
        index, keep = on_model_map(m.previous_pixels, world, model, self.params.anchor_distance_m,
                                   None if at is field else at)
        solved, in_solve = solved_index(index, model.visible)
        keep &= in_solve
        index = index[keep]
        ref, _ = inverse_warp(world[keep], None, model.knn[index], model.weights[index], at)
        return AnchoredMatches(solved[keep], ref, m.current_points[keep], np.full(len(ref), weight))


def on_model_map(pixels: np.ndarray, points_world: np.ndarray, model: ModelView, max_distance_m: float,
                 field: WarpField | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(model index, keep) of features seen at `pixels` of the last frame: the surfel the model
    map shows there, kept where it lies within max_distance_m of the feature's depth point (the
    model and that frame agree), the surfel where `field` puts it if given, else where it is."""
    index = pixel_values(pixels, model.index_map).astype(np.int64)
    i = np.maximum(index, 0)
    live = model.live_position[i] if field is None else \
        warp(model.ref_position[i], None, model.knn[i], model.weights[i], field)[0]
    return index, (index >= 0) & (np.linalg.norm(live - points_world, axis=1) < max_distance_m)
