"""The warp field's common rigid motion moved into the camera pose (tracker.Tracker.factor)."""
from __future__ import annotations

import numpy as np

from surfelwarp.deform.warp_field import WarpField, to_local
from surfelwarp.geometry.se3 import fit_rigid, fit_rigid_informed, invert
from surfelwarp.tracking.degeneracy import HeldDirections


def factor_rigid_motion(field: WarpField, node_weights: np.ndarray | None = None,
                        rest_points: np.ndarray | None = None,
                        held: HeldDirections | None = None) -> tuple[WarpField, np.ndarray]:
    """Split W = A o W' with A the rigid motion best fitting the nodes' displacements from
    rest_points (default: the nodes themselves), weighted by node_weights: (M,) weights, or
    (M, 3, 3) information (each node counts along the directions its data measures,
    se3.fit_rigid_informed); without its components along the `held` directions (they stay
    in the field: the camera does not move where the data cannot say).

    DQB commutes with a common left factor, so W' = A^-1 o W exactly. Without this, rigid
    tracking error that the non-rigid solve absorbs would stay in the warp field forever and
    the camera pose would drift from the composite motion that is actually tracked. Weighted by
    data support, A is the seen nodes' common motion even when most nodes are out of view (a
    room); fitted to every node alike it is only part of it, and the rest stays in their
    transforms. Weighted by information, a node's slide along its surface, which its depth
    does not see (the regulariser's pull, a colour pair's), stays in the field too.
    """
    source = field.nodes if rest_points is None else rest_points
    fit = fit_rigid_informed if node_weights is not None and np.ndim(node_weights) == 3 else fit_rigid
    A = fit(source, field.live_nodes(), node_weights)
    if held is not None:
        A = held.project(A)
    G = invert(A) @ field.global_transforms()
    return field.with_transforms(to_local(G, field.nodes)), A
