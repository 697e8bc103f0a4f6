"""Rest anchors: warp nodes the depth shows at rest are held at their rest transform.

Not in either paper. The data term and the graph regulariser (SurfelWarp Eq. 8) leave the
field free to bend wherever depth is noisy or inconsistent, and every bend is carried into the
reference by inverse warping, so on a static room seen by a moving camera the field and the
pose random-walk together (7-Scenes: 8.1 cm ATE over 200 frames, against 4.8 cm for rigid ICP
alone). An anchored node j adds

    E_anchor = mu sum_a |L_j y_a - Rest_j y_a|^2,   y_a in {0, sigma e_x, sigma e_y, sigma e_z}

(node-local points, sigma the skinning radius) to the solve: the same units as the data term,
so mu = 1 weighs a node's rest like one depth pair per anchor point. A node is released
(mu = 0) in a frame's first Gauss-Newton iteration when the step the data alone asks for
would move it more than release_sigmas times the sensor's axial noise at its depth from its
rest: real motion leaves the noise behind within a frame, noise does not. A released node
that then moves less than settle_sigmas a frame for settle_frames frames in a row is anchored
again at its new transform, so a hand that moves and stops stops drifting too. The tracker
moves into the camera pose the rigid motion that returns the anchored nodes to rest.

Off by default: on the waving sheet, nodes settle where the wave turns and then lag until
the data pulls them release_sigmas away (EPE 11.9 mm against 4.1 mm; README).

Nodes added by warp-field extension take the released flag of their nearest old node and
their birth transform as rest; a rebuilt field (reinitialisation) starts anchored at rest.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pykdtree.kdtree import KDTree

from .camera import axial_noise_sigma_m
from .se3 import invert, transform_points
from .warp_field import WarpField


@dataclass(frozen=True)
class AnchorParams:
    weight: float = 0.0             # mu; 0: no anchors (the papers' solve); 1 for a mostly static scene
    release_sigmas: float = 2.0     # release when data alone moves a node this many sigma(z) from rest
    settle_sigmas: float = 1.0      # re-anchor a released node that moves less than this many sigma(z) ...
    settle_frames: int = 3          # ... a frame for this many frames in a row


@dataclass(frozen=True)
class AnchorTerm:
    """What the Gauss-Newton solve needs, per node of the solved field."""
    mu: np.ndarray          # (M,) anchor weight (0: free)
    rest: np.ndarray        # (M, 4, 4) node-local rest transforms
    release_m: np.ndarray   # (M,) free-step distance from rest that releases an anchored node


def anchor_offsets(sigma_m: float) -> np.ndarray:
    """(4, 3) the node-local points y_a: the node and sigma along each axis."""
    return sigma_m * np.vstack([np.zeros(3), np.eye(3)])


def _apply(transforms: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("mab,kb->mka", transforms[:, :3, :3], y) + transforms[:, None, :3, 3]


def anchor_residuals(transforms: np.ndarray, rest: np.ndarray, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 4, 3) L_j y_a - Rest_j y_a, and the points L_j y_a."""
    y = anchor_offsets(sigma_m)
    z = _apply(transforms, y)
    return z - _apply(rest, y), z


def deviation_m(transforms: np.ndarray, rest: np.ndarray, sigma_m: float) -> np.ndarray:
    """(M,) the largest distance of a node's anchor points from where `rest` puts them."""
    r, _ = anchor_residuals(transforms, rest, sigma_m)
    return np.linalg.norm(r, axis=-1).max(axis=1)


def node_depth_m(field: WarpField, T_camera_to_world: np.ndarray) -> np.ndarray:
    """(M,) depth of each live node in the camera (at least 0.3 m, the sensor's near limit)."""
    z = transform_points(invert(T_camera_to_world), field.live_nodes())[:, 2]
    return np.maximum(z, 0.3)


@dataclass(frozen=True, eq=False)
class NodeAnchors:
    """Anchor state of a field's nodes, carried from frame to frame by the tracker."""
    nodes: np.ndarray         # (M, 3) the field nodes this state belongs to
    rest: np.ndarray          # (M, 4, 4)
    released: np.ndarray      # (M,) bool
    previous: np.ndarray      # (M, 4, 4) the transforms at the end of the last frame
    still_frames: np.ndarray  # (M,) int frames in a row a released node has barely moved

    @classmethod
    def at_rest(cls, field: WarpField) -> "NodeAnchors":
        m = field.num_nodes
        return cls(field.nodes, field.transforms.copy(), np.zeros(m, bool), field.transforms.copy(),
                   np.zeros(m, np.int64))

    def follow(self, field: WarpField) -> "NodeAnchors":
        """This state for `field`: the same if its nodes are ours, extended if it only appended
        nodes, anchored at rest if it is a new field."""
        if field.nodes is self.nodes:
            return self
        m0, m = len(self.nodes), field.num_nodes
        if m < m0 or not np.array_equal(field.nodes[:m0], self.nodes):
            return NodeAnchors.at_rest(field)
        born = field.transforms[m0:]
        _, nearest = KDTree(self.nodes).query(field.nodes[m0:], k=1)
        return NodeAnchors(field.nodes, np.concatenate([self.rest, born]),
                           np.concatenate([self.released, self.released[nearest.astype(np.int64)]]),
                           np.concatenate([self.previous, born]),
                           np.concatenate([self.still_frames, np.zeros(m - m0, np.int64)]))

    def term(self, params: AnchorParams, depth_m: np.ndarray, num_solved: int) -> AnchorTerm:
        """The solve's anchor term; nodes beyond ours (a deformation tree's upper levels) are free."""
        m, extra = len(self.nodes), num_solved - len(self.nodes)
        mu = np.concatenate([params.weight * ~self.released, np.zeros(extra)])
        rest = np.concatenate([self.rest, np.tile(np.eye(4), (extra, 1, 1))])
        release = params.release_sigmas * axial_noise_sigma_m(depth_m[:m])
        return AnchorTerm(mu, rest, np.concatenate([release, np.full(extra, np.inf)]))

    def release(self, released: np.ndarray) -> "NodeAnchors":
        return replace(self, released=self.released | released[:len(self.nodes)])

    def settle(self, field: WarpField, depth_m: np.ndarray, params: AnchorParams) -> "NodeAnchors":
        """End of frame: count the frames released nodes barely move; anchor those that settled."""
        moved = deviation_m(field.transforms, self.previous, field.sigma_m)
        still = self.released & (moved < params.settle_sigmas * axial_noise_sigma_m(depth_m))
        frames = np.where(still, self.still_frames + 1, 0)
        back = frames >= params.settle_frames
        rest = np.where(back[:, None, None], field.transforms, self.rest)
        return NodeAnchors(field.nodes, rest, self.released & ~back, field.transforms, np.where(back, 0, frames))
