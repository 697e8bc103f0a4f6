"""Rest anchors: warp nodes the depth shows at rest are held at their rest transform, up to
one rigid motion they share.

Not in either paper. The data term and the graph regulariser (SurfelWarp Eq. 8) leave the
field free to bend wherever depth is noisy or inconsistent, and every bend is carried into the
reference by inverse warping, so on a static room seen by a moving camera the field and the
pose random-walk together (7-Scenes: 8.1 cm ATE over 200 frames without anchors, against
4.8 cm for rigid ICP alone). An anchored node j adds

    E_anchor = mu sum_a |L_j y_a - G Rest_j y_a|^2,   y_a in {0, sigma e_x, sigma e_y, sigma e_z}

(node-local points moved to world, sigma the skinning radius) to the solve: the same units as
the data term, so mu = 1 weighs a node's rest like one depth pair per anchor point. G is one
world rigid motion shared by all anchored nodes and solved with them: what rigid ICP left of
the camera's motion, so a pose error neither pulls against the anchors nor releases them.

A node is released (mu = 0) in a frame's first Gauss-Newton iteration when the step the data
alone asks for would move it more than release_sigmas times the sensor's axial noise at its
depth from G Rest_j, G then being the rigid motion of the supported anchored nodes that stay
within that distance of it: real motion leaves the noise behind within a frame, noise does not.
Only nodes with depth pairs of their own (release_support) are released: at the edge of the
view the step moves nodes through the regulariser alone. A released node the solve leaves
within its release distance of rest is anchored at rest again at the end of the frame (on
7-Scenes the releases are systematic near the camera and at the edge of the view, and the
released nodes rarely settled: ATE 4.47 cm, 4.05 with this). A released node that stays within
settle_sigmas of one transform for settle_frames frames in a row is anchored again there, so a
hand that moves and stops stops drifting too; measured from where the still run began, not
frame to frame, so that a node slowing down where a wave turns is not anchored while it still
creeps. The tracker moves into the camera pose the rigid motion that returns the anchored nodes
to rest (about G). Nodes held out of the solve (out of view) follow G, as rigid ICP's motion
would move them.

Nodes added by warp-field extension are anchored at their birth transform (if they move, the
next frame's first iteration releases them); a rebuilt field (reinitialisation) starts
anchored at rest.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numba
import numpy as np

from surfelwarp.deform.warp_field import WarpField, to_global, to_local
from surfelwarp.geometry.camera import axial_noise_sigma_m
from surfelwarp.geometry.se3 import fit_rigid, invert, transform_points
from surfelwarp.tracking.degeneracy import HeldDirections


@dataclass(frozen=True)
class AnchorParams:
    weight: float = 1.0             # mu; 0: no anchors (the papers' solve)
    release_sigmas: float = 2.0     # release when data alone moves a node this many sigma(z) from rest,
    release_support: float = 5.0    # and its pairs' skinning weights sum to at least this
    settle_sigmas: float = 1.0      # re-anchor a released node that stays within this many sigma(z)
    settle_frames: int = 10         # of one transform for this many frames in a row
    common_motion: bool = True      # rest follows one rigid motion solved with the nodes (False:
                                    # rest itself, so a pose error releases still nodes)
    # The release distance counts the directions a node's own depth pairs measure (their
    # normals) in full and the others at this weight (squared distance; 1: the whole step counts
    # alike): a flat table top's nodes, slid along the table by the graph from an arm moving
    # above it, were released by the hundred (table at 320x240: 40 % of the nodes released, the
    # camera 12.8 mm off). Largest camera error on that table over 90 frames (and over the first
    # 20, tests/test_hard_scenes.py) at weight 1: 12.8 mm (3.8), 0.5: 7.5 (4.2), 0.25: 5.3
    # (4.5), 0.1: 7.4 (5.0), 0: 6.9; at 0 a rolling sheet's nodes, whose first step runs mostly
    # along their surface, were not released (tests/tracking/test_anchors.py).
    release_unseen_weight: float = 0.25
    # The release test's free step is solved by PCG to this relative residual, not to the
    # solve's pcg_rtol: it only sorts nodes by a distance of millimetres. On 7-Scenes (9k nodes)
    # 66-98 PCG iterations at 1e-4 (the solve's own steps 17-31), 19-30 at 1e-2, the released
    # nodes the same but for those at the threshold; 200 frames 1202 -> 1073 ms a frame, ATE
    # 3.87 -> 3.80 cm; the synthetic scenes' moving EPE within -15 % (roll) to +4 % (fast).
    release_step_rtol: float = 1e-2

    ZERO_OK = {"weight", "release_support", "settle_sigmas", "settle_frames", "release_unseen_weight"}
    UNIT = {"release_unseen_weight", "release_step_rtol"}


@dataclass(frozen=True)
class AnchorTerm:
    """What the Gauss-Newton solve needs, per node of the solved field."""
    mu: np.ndarray          # (M,) anchor weight (0: free)
    rest: np.ndarray        # (M, 4, 4) node-local rest transforms
    release_m: np.ndarray   # (M,) free-step distance from rest that releases an anchored node
    release_support: float = 0.0     # ... if its pairs' skinning weights sum to at least this
    common_motion: bool = True   # rest follows a rigid motion solved with the nodes
    held: HeldDirections | None = None   # ... not along these (rigid ICP's, degeneracy.py)
    release_unseen_weight: float = 1.0  # ... counting unseen directions at this weight
    release_step_rtol: float | None = None  # ... the free step solved to this PCG tolerance (None: the solve's)


def anchor_offsets(sigma_m: float) -> np.ndarray:
    """(4, 3) the node-local points y_a: the node and sigma along each axis."""
    return sigma_m * np.vstack([np.zeros(3), np.eye(3)])


def _apply(transforms: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(M, K, 3) each transform (M, 4, 4) applied to each point y (K, 3). A product per output
    axis: einsum over the strided 3x3 blocks took 2.5 ms a call on 6.7k nodes, this 0.3 ms
    (the anchors' energy runs ~30 times a 7-Scenes frame)."""
    yh = np.vstack([np.asarray(y, np.float64).T, np.ones(len(y))])
    out = np.empty((len(transforms), len(y), 3))
    for a in range(3):
        out[:, :, a] = transforms[:, a, :] @ yh
    return out


def anchor_residuals(transforms: np.ndarray, rest: np.ndarray, sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 4, 3) L_j y_a - Rest_j y_a, and the points L_j y_a."""
    y = anchor_offsets(sigma_m)
    z = _apply(transforms, y)
    return z - _apply(rest, y), z


def deviation_m(transforms: np.ndarray, rest: np.ndarray, sigma_m: float) -> np.ndarray:
    """(M,) the largest distance of a node's anchor points from where `rest` puts them."""
    r, _ = anchor_residuals(transforms, rest, sigma_m)
    return np.linalg.norm(r, axis=-1).max(axis=1)


def node_information(num_nodes: int, knn: np.ndarray, weights: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(M, 3, 3) per node, what its depth pairs measure of its motion: the skinning-weighted sum
    of the pairs' n n^T over the pairs' nodes knn (C, K) and weights (C, K), normals (C, 3) (its
    trace: the pairs' skinning weight on the node)."""
    S = np.zeros((num_nodes, 9))
    _sum_outer(np.ascontiguousarray(knn, np.int64), np.ascontiguousarray(weights, np.float64),
               np.ascontiguousarray(normals, np.float64), S)
    return S.reshape(-1, 3, 3)


def seen_directions(num_nodes: int, knn: np.ndarray, weights: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(M, 3, 3) per node, the directions its depth pairs measure: node_information scaled to a
    largest eigenvalue of 1 (a plane: n n^T; a cylinder: all but its axis; a ball: the
    identity); 0 for a node without pairs."""
    S = node_information(num_nodes, knn, weights, normals)
    top = np.linalg.eigvalsh(S)[:, -1]
    return S / np.where(top > 0, top, 1.0)[:, None, None]


@numba.njit(cache=True, nogil=True)
def _sum_outer(knn, weights, n, S):
    """S[node] += w n n^T for each pair's nodes, pair after pair: the order (and so every bit)
    of np.bincount's sums over the raveled knn, nine of which took ~4 ms a sheet frame."""
    for c in range(knn.shape[0]):
        for s in range(knn.shape[1]):
            node, w = knn[c, s], weights[c, s]
            for a in range(3):
                for b in range(3):
                    S[node, 3 * a + b] += w * (n[c, a] * n[c, b])


def seen_deviation_m(transforms: np.ndarray, rest: np.ndarray, sigma_m: float, seen: np.ndarray) -> np.ndarray:
    """(M,) deviation_m counting only the seen directions (M, 3, 3) of seen_directions."""
    r, _ = anchor_residuals(transforms, rest, sigma_m)
    return np.sqrt(np.maximum(np.einsum("mka,mab,mkb->mk", r, seen, r), 0.0)).max(axis=1)


def follow_motion(transforms: np.ndarray, nodes: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(M, 4, 4) node-local transforms followed by the world rigid motion G."""
    return to_local(G @ to_global(transforms, nodes), nodes)


def anchor_points(transforms: np.ndarray, nodes: np.ndarray, sigma_m: float) -> np.ndarray:
    """(M, 4, 3) the world points p_j + L_j y_a."""
    return np.asarray(nodes, np.float64)[:, None, :] + _apply(transforms, anchor_offsets(sigma_m))


def common_motion(transforms: np.ndarray, rest: np.ndarray, nodes: np.ndarray, sigma_m: float,
                  weights: np.ndarray, inlier_m: np.ndarray, rounds: int = 3) -> np.ndarray:
    """The world rigid motion G best taking the nodes' rest anchor points to those of
    `transforms` (Kabsch, weighted), refitted to the nodes within inlier_m of it: the motion
    the still part shares, which the moving part must not drag."""
    source = anchor_points(rest, nodes, sigma_m).reshape(-1, 3)
    target = anchor_points(transforms, nodes, sigma_m)
    w = np.asarray(weights, np.float64)
    G = np.eye(4)
    for _ in range(rounds):
        if np.count_nonzero(w) < 1:
            break
        G = fit_rigid(source, target.reshape(-1, 3), np.repeat(w, 4))
        # deviation_m from the rest followed by G, whose anchor points are G's image of the
        # rest's: the same distances to rounding (the same runs to the bit), without
        # follow_motion's and deviation_m's node-local products (a call on 9k nodes 16.5 -> 7.7 ms)
        d = target - transform_points(G, source).reshape(target.shape)
        inside = np.sqrt(np.einsum("mai,mai->ma", d, d).max(axis=1)) <= inlier_m
        if not inside.any():
            break
        w = np.where(inside, weights, 0.0)
    return G


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
    origin: np.ndarray        # (M, 4, 4) where a released node's still run began (else its
                              # transform at the end of the last frame)
    still_frames: np.ndarray  # (M,) int frames in a row a released node stayed near its origin
    # (M,) how still each node is, for the camera: 0 released, else 1 - its distance from rest
    # in units of its release distance (a part that starts to move weighs less before it is
    # released); None: 1 for the anchored nodes.
    stillness: np.ndarray | None = None

    def still_weights(self) -> np.ndarray:
        return (~self.released).astype(np.float32) if self.stillness is None else self.stillness

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
        return NodeAnchors(field.nodes, np.concatenate([self.rest, born]),
                           np.concatenate([self.released, np.zeros(m - m0, bool)]),
                           np.concatenate([self.origin, born]),
                           np.concatenate([self.still_frames, np.zeros(m - m0, np.int64)]),
                           np.concatenate([self.still_weights(), np.ones(m - m0, np.float32)]))

    def term(self, params: AnchorParams, depth_m: np.ndarray, num_solved: int,
             held: HeldDirections | None = None) -> AnchorTerm:
        """The solve's anchor term; nodes beyond ours (a deformation tree's upper levels) are free."""
        m, extra = len(self.nodes), num_solved - len(self.nodes)
        mu = np.concatenate([params.weight * ~self.released, np.zeros(extra)])
        rest = np.concatenate([self.rest, np.tile(np.eye(4), (extra, 1, 1))])
        release = params.release_sigmas * axial_noise_sigma_m(depth_m[:m])
        return AnchorTerm(mu, rest, np.concatenate([release, np.full(extra, np.inf)]), params.release_support,
                          params.common_motion, held, params.release_unseen_weight, params.release_step_rtol)

    def release(self, released: np.ndarray) -> "NodeAnchors":
        released = self.released | released[:len(self.nodes)]
        return replace(self, released=released, stillness=np.where(released, 0.0, self.still_weights()))

    def settle(self, field: WarpField, depth_m: np.ndarray, params: AnchorParams) -> "NodeAnchors":
        """End of frame: count the frames released nodes stay near their origin; anchor those
        that settled; a node that left its origin starts a new run where it is."""
        moved = deviation_m(field.transforms, self.origin, field.sigma_m)
        # A released node the solve left within its release distance of rest did not move
        # beyond the noise: it is anchored at rest again (if it moves, the next frame's first
        # iteration releases it again, before the solve).
        home = self.released & (deviation_m(field.transforms, self.rest, field.sigma_m)
                                < params.release_sigmas * axial_noise_sigma_m(depth_m))
        still = self.released & ~home & (moved < params.settle_sigmas * axial_noise_sigma_m(depth_m))
        frames = np.where(still, self.still_frames + 1, 0)
        back = frames >= params.settle_frames
        rest = np.where(back[:, None, None], field.transforms, self.rest)
        origin = np.where((still & ~back)[:, None, None], self.origin, field.transforms)
        released = self.released & ~back & ~home
        away = deviation_m(field.transforms, rest, field.sigma_m) / (params.release_sigmas * axial_noise_sigma_m(depth_m))
        stillness = np.where(released, 0.0, np.clip(1.0 - away, 0.0, 1.0)).astype(np.float32)
        return NodeAnchors(field.nodes, rest, released, origin, np.where(back, 0, frames), stillness)
