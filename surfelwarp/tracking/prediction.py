"""Constant velocity per node: each node the last solve saw move starts the next frame moved on
by its last step, as a tracker predicts before it measures.

The solve's depth pairs reach 3 cm (NonRigidParams.distance_gate_m). Where the camera's pose
follows the scene (an object alone), rigid ICP carries a fast object's motion; before a still
background, which holds the pose, the object's nodes start each frame where the last one left
them, and a ball moving 4.5 cm a frame is left behind (`fast-wall`: mean EPE 88 mm on the ball
over 60 frames without, 1.0-3.0 mm with). Only the nodes' positions are carried on: their turns,
which depth sees poorly on a round object, compounded into a lost ball within a few frames
when carried on too.

A prediction is checked before it is used (`carry_on`), as a tracker gates its prediction by
the measurement: a node keeps its step only where its surfels find at least as many depth
pairs from there as from where the last frame left them. Where the motion turns at once (a
ball bouncing back at 3 cm a frame), the step would throw the node twice as far from the
surface as it is. A step within twice the depth noise at its node is not carried on at all:
it is not told from noise (7-Scenes' still room releases ~1000 nodes a frame that step 1-3
mm), and the solve finds so short a motion from where the last frame left it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from surfelwarp.deform.warp_field import WarpField, warp
from surfelwarp.geometry.camera import axial_noise_sigma_m
from surfelwarp.geometry.dual_quaternion import _components
from surfelwarp.tracking.anchors import node_depth_m
from surfelwarp.tracking.association import DepthTargets, associate_components


def carried_nodes(information: np.ndarray | None, released: np.ndarray | None) -> np.ndarray | None:
    """(M,) bool the nodes whose last step is carried on: those the solve's depth pairs measured
    ((M, 3, 3) information; a node out of view keeps no step, since no data would correct it),
    and of those, with rest anchors, the released ones (an anchored node is still by their
    account). None without information."""
    if information is None:
        return None
    seen = np.trace(information, axis1=1, axis2=2) > 0
    return seen if released is None else seen & released[:len(seen)]


@dataclass
class NodeMotion:
    share: float                                       # of the last step carried on (0: none)
    ended: tuple[np.ndarray, np.ndarray] | None = None  # the last frame's nodes and their live
                                                       # positions when it ended
    steps: np.ndarray | None = None                    # (m, 3) its first m nodes' steps over it
                                                       # (zero: not carried on)
    min_step_sigmas: float = 0.0                       # a step no longer than this many sigma
                                                       # of the depth noise at its node is not
                                                       # carried on: not told from noise,
    reach_m: float = np.inf                            # unless longer than the solve's pairs'
                                                       # reach, which they cannot bridge (2
                                                       # sigma passes 3 cm beyond 3.1 m)

    def end_frame(self, field: WarpField, carried: np.ndarray | None, T_camera_to_world: np.ndarray) -> None:
        """Record the frame's end: each node's step since the last end where `carried` (M,) and
        the step is longer than min_step_sigmas of the depth noise at the node (seen from
        T_camera_to_world) or than reach_m; none if the field's first nodes are not
        those that frame ended with (a new field)."""
        last, self.steps = self.ended, None
        m = 0 if last is None else len(last[0])
        live = field.live_nodes()
        if carried is not None and last is not None and m <= field.num_nodes \
                and np.array_equal(field.nodes[:m], last[0]):
            steps = live[:m] - last[1]
            floor = np.minimum(self.min_step_sigmas * axial_noise_sigma_m(node_depth_m(field, T_camera_to_world)[:m]),
                               self.reach_m)
            self.steps = np.where((carried[:m] & (np.linalg.norm(steps, axis=1) > floor))[:, None], steps, 0.0)
        self.ended = (field.nodes, live)

    def predicted(self, field: WarpField) -> WarpField:
        """`field` with each node moved on by `share` of its last step (the nodes the last frame
        ended with keep their indices; those born since stay); `field` itself if none moves."""
        steps = self.steps
        if steps is None or self.share == 0 or len(steps) > field.num_nodes \
                or not np.array_equal(field.nodes[:len(steps)], self.ended[0][:len(steps)]):
            return field
        moving = np.flatnonzero(np.any(steps != 0, axis=1))
        if len(moving) == 0:
            return field
        transforms = field.transforms.copy()
        transforms[moving, :3, 3] += self.share * steps[moving]
        return field.with_transforms(transforms)


def moved_nodes(field: WarpField, start: WarpField) -> np.ndarray:
    """(M,) bool the nodes whose transform differs between the two fields."""
    return np.any(start.transforms != field.transforms, axis=(1, 2))


@numba.njit(cache=True, nogil=True)
def _skinned_sums(knn, weights, index, num_nodes):
    """(num_nodes,) the skinning weights of the rows `index` summed by node, as np.bincount of
    the raveled rows sums them (the same order: the same bits), without their gathered copies."""
    out = np.zeros(num_nodes)
    for i in index:
        for j in range(knn.shape[1]):
            out[knn[i, j]] += weights[i, j]
    return out


def carry_on(field: WarpField, start: WarpField, points: np.ndarray, normals: np.ndarray, knn: np.ndarray,
             weights: np.ndarray, live: np.ndarray, live_normals: np.ndarray, targets: DepthTargets,
             distance_gate_m: float, min_normal_cos: float) -> WarpField:
    """The field a frame starts from: `start` (NodeMotion.predicted of `field`) with each node it
    moved put back where `field` has it unless the surfels it skins (reference points, normals,
    knn, weights) find, weighed by their skinning, at least as many depth pairs (`targets`, the
    solve's gate) from the start as from where `field` puts them. The model's live points and
    normals (`live`, `live_normals`, (N, 3)) of the surfels the returned field moves are
    warped again, in place (the check's own warp of them where it can); the others keep
    theirs (fused)."""
    if start is field:
        return field
    moved = moved_nodes(field, start)
    kind = np.empty(len(knn), np.int8)
    _row_kinds(moved, np.zeros_like(moved), knn, kind)     # KEPT: a row with a moved node
    hit = kind == KEPT
    count = int(hit.sum())
    if count == 0:
        return start
    # Where most surfels moved (an object alone) all are warped and checked, not gathered: a
    # surfel without a moved node adds only to nodes the check does not look at.
    rows = slice(None) if 2 * count > len(knn) else np.flatnonzero(hit)
    points, normals, knn, weights = points[rows], normals[rows], knn[rows], weights[rows]
    ahead, ahead_n = warp(points, normals, knn, weights, start)

    def support(p: np.ndarray, n: np.ndarray) -> np.ndarray:
        pairs = associate_components(_components(p), _components(n), targets, distance_gate_m, min_normal_cos)
        return _skinned_sums(knn, weights, pairs.index, field.num_nodes)

    back = moved & (support(ahead, ahead_n) < support(*warp(points, normals, knn, weights, field)))
    kind = np.empty(len(knn), np.int8)
    _row_kinds(moved & ~back, back, knn, kind)
    if back.any():
        transforms = start.transforms.copy()
        transforms[back] = field.transforms[back]
        start = start.with_transforms(transforms)
        # A surfel with a node put back and one kept is warped by the field as it ends up; one
        # with only nodes put back keeps its live values.
        mixed = np.flatnonzero(kind == MIXED)
        if len(mixed):
            ahead[mixed], ahead_n[mixed] = warp(points[mixed], normals[mixed], knn[mixed], weights[mixed], start)
    index, keep = np.arange(len(live))[rows], np.flatnonzero(kind <= MIXED)
    _put_rows(live, ahead, index, keep)
    _put_rows(live_normals, ahead_n, index, keep)
    return start


KEPT, MIXED, PUT_BACK, UNMOVED = 0, 1, 2, 3


@numba.njit(cache=True, nogil=True)
def _row_kinds(kept, back, knn, kind):
    """kind[i] of row i: MIXED with a node `back` and one `kept`, else KEPT, PUT_BACK or
    UNMOVED (neither)."""
    for i in range(len(knn)):
        k = b = False
        for j in range(knn.shape[1]):
            k |= kept[knn[i, j]]
            b |= back[knn[i, j]]
        kind[i] = MIXED if k and b else (KEPT if k else (PUT_BACK if b else UNMOVED))


@numba.njit(cache=True, nogil=True)
def _put_rows(dst, src, index, sel):
    """dst[index[i]] = src[i] for i in sel (numpy's gather and scatter of (N, 3) rows by index
    arrays take ~1 ms each on 66k rows)."""
    for i in sel:
        for c in range(dst.shape[1]):
            dst[index[i], c] = src[i, c]
