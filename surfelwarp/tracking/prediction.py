"""Constant velocity per node: each node the last solve saw move starts the next frame moved on
by its last step, as a tracker predicts before it measures.

The solve's depth pairs reach 3 cm (NonRigidParams.distance_gate_m). Where the camera's pose
follows the scene (an object alone), rigid ICP carries a fast object's motion; before a still
background, which holds the pose, the object's nodes start each frame where the last one left
them, and a ball moving 4.5 cm a frame is left behind (`fast-wall`: mean EPE 88 mm on the ball
over 60 frames without, 1.7 mm with). Only the nodes' positions are carried on: their turns,
which depth sees poorly on a round object, compounded into a lost ball within a few frames
when carried on too.

A prediction is checked before it is used (`confirmed`), as a tracker gates its prediction by
the measurement: a node keeps its step only where its surfels find at least as many depth
pairs from there as from where the last frame left them. Where the motion turns at once (a
ball bouncing back at 3 cm a frame), the step would throw the node twice as far from the
surface as it is.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelwarp.deform.warp_field import WarpField, warp
from surfelwarp.geometry.dual_quaternion import _components
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

    def end_frame(self, field: WarpField, carried: np.ndarray | None) -> None:
        """Record the frame's end: each node's step since the last end where `carried` (M,),
        none if the field's first nodes are not those that frame ended with (a new field)."""
        last, self.steps = self.ended, None
        m = 0 if last is None else len(last[0])
        live = field.live_nodes()
        if carried is not None and last is not None and m <= field.num_nodes \
                and np.array_equal(field.nodes[:m], last[0]):
            self.steps = np.where(carried[:m, None], live[:m] - last[1], 0.0)
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


def rows_of(moved: np.ndarray, knn: np.ndarray) -> np.ndarray:
    """The rows of the skinning `knn` (N, k) with a `moved` node: the surfels a prediction
    moved, to warp again."""
    hit = moved[knn[:, 0]]
    for j in range(1, knn.shape[1]):    # a column at a time: 3x faster than any(axis=1) on a room
        hit |= moved[knn[:, j]]
    return np.flatnonzero(hit)


def warp_moved(field: WarpField, predicted: WarpField, points: np.ndarray, normals: np.ndarray, knn: np.ndarray,
               weights: np.ndarray, live: np.ndarray, live_normals: np.ndarray) -> None:
    """The live points and normals (N, 3, in place) of the rows whose nodes `predicted` moved
    from `field`, warped again from their reference ones; the others keep theirs (fused)."""
    if predicted is field:
        return
    rows = rows_of(moved_nodes(field, predicted), knn)
    if len(rows):
        live[rows], live_normals[rows] = warp(points[rows], normals[rows], knn[rows], weights[rows], predicted)


def confirmed(field: WarpField, start: WarpField, points: np.ndarray, normals: np.ndarray, knn: np.ndarray,
              weights: np.ndarray, targets: DepthTargets, distance_gate_m: float, min_normal_cos: float
              ) -> WarpField:
    """`start` (NodeMotion.predicted of `field`) with each node it moved put back where `field`
    has it unless the surfels it skins (reference points, normals, knn, weights) find, weighed
    by their skinning, at least as many depth pairs (`targets`, the solve's gate) from the
    start as from `field`."""
    moved = moved_nodes(field, start)
    rows = rows_of(moved, knn)
    if len(rows) == 0:
        return start
    knn, weights = knn[rows], weights[rows]

    def support(f: WarpField) -> np.ndarray:
        live, live_n = warp(points[rows], normals[rows], knn, weights, f)
        pairs = associate_components(_components(live), _components(live_n), targets, distance_gate_m, min_normal_cos)
        return np.bincount(knn[pairs.index].ravel(), weights[pairs.index].ravel(), minlength=field.num_nodes)

    back = moved & (support(start) < support(field))
    if not back.any():
        return start
    transforms = start.transforms.copy()
    transforms[back] = field.transforms[back]
    return start.with_transforms(transforms)
