"""The tracker both methods share: each moving node carried on by its last step (prediction.py),
colour correspondences (colour.py), rigid ICP (the colour pairs moving the pose along what its
depth cannot see), then non-rigid Gauss-Newton (with rest anchors, anchors.py, unless their
weight is 0; started by a solve the colour pairs lead when they lie beyond the depth term's
reach), then the warp field's common rigid motion moved into the camera pose.

Pose conventions: `T_camera_to_world` maps this frame's camera points into the world (the first
frame's camera); twists are (omega, v), rotation first (geometry/se3.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from surfelwarp.deform.hierarchy import Hierarchy, HierarchyParams, build_hierarchy, with_hierarchy
from surfelwarp.deform.warp_field import WarpField, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, transform_points
from surfelwarp.preprocess import CameraObservation
from surfelwarp.tracking.anchors import AnchorParams, NodeAnchors, follow_motion, node_depth_m
from surfelwarp.tracking.degeneracy import HeldDirections
from surfelwarp.tracking.colour import ColourMatcher
from surfelwarp.tracking.factoring import factor_rigid_motion
from surfelwarp.tracking.features import AnchoredMatches, FeatureParams, ModelView
from surfelwarp.tracking.ahead import FoundAhead
from surfelwarp.tracking.association import DepthTargets
from surfelwarp.tracking.free_space import FreeSpace
from surfelwarp.tracking.gauss_newton import NonRigidParams, NonRigidResult, solve_nonrigid
from surfelwarp.tracking.prediction import NodeMotion, carried_nodes, carry_on
from surfelwarp.tracking.rigid_icp import PointPairs, RigidParams, RigidResult, rigid_icp
from surfelwarp.tracking.stillness import (covered_share, point_stillness, rigid_weight, rigid_weight_map,
                                          stillness_map)


CAMERAS = ("moving", "static")


@dataclass(frozen=True)
class TrackingParams:
    # 'moving': the camera pose is estimated; 'static': it stays the identity and every motion
    # is the warp field's (rigid ICP then only gives the solve a second start, the scene's
    # common motion).
    camera: str = "moving"
    rigid: RigidParams = field(default_factory=RigidParams)
    nonrigid: NonRigidParams = field(default_factory=NonRigidParams)
    # Start rigid ICP from a constant-velocity prediction. Off: on deforming scenes the "camera
    # motion" is partly deformation, and extrapolating it pushes the model along directions depth
    # does not observe (the sheet: lost at frame 35 with it, 1.9 mm mean EPE over 90 without).
    predict_motion: bool = False
    factor_rigid_motion: bool = True   # move the warp field's common rigid motion into the pose
    factor_by_support: bool = True     # that motion fitted to the nodes the depth constrains, each
                                       # along the directions its pairs measure (their normals'
                                       # n n^T, skinning-weighted; False: every node alike, whole)
    # DynamicFusion's deformation tree as the regulariser (deform/hierarchy.py): in place of SurfelWarp's
    # k-nearest-node graph (Eq. 10), or on top of it with hierarchy.keep_graph; off: the graph.
    hierarchy: HierarchyParams = field(default_factory=HierarchyParams)
    anchor: AnchorParams = field(default_factory=AnchorParams)   # weight 0: off (the papers' solve)
    # Rigid ICP weighs the model surface skinned to released (moving) nodes this much against
    # the anchored (still) surface: the parts that hold still decide the camera's motion, and a
    # bending limb no longer pushes it. Everything moving: all weigh alike, as without anchors.
    released_rigid_weight: float = 0.05
    # Below this share of still (anchored) surface in view there is no evidence of the camera's
    # motion: it is held, and rigid ICP's motion is the scene's (as with a static camera).
    min_still_share: float = 0.1
    # Colour features matched from frame to frame (tracking/features.py); their weight in the
    # solve is nonrigid.feature_weight (0: colour is not used).
    features: FeatureParams = field(default_factory=FeatureParams)
    # The colour pairs also move the camera's pose along the directions rigid ICP's depth held
    # (a flat wall's slide: wall-slide's ATE 17.2 -> 0.03 cm), each weighed by its stillness;
    # False: the pose from depth alone. (Beside the depth in every direction they cost orbit's
    # ATE, 0.41 -> 0.48 cm, and the shirt pair 2.9 mm.)
    colour_pose: bool = True
    # ... where they lie over at least this share of the still surface in view (as rigid ICP
    # weighs it, stillness.covered_share; 0: always): the pairs of a textured limb sliding along
    # itself before a plain wall (a share of ~0.05) moved the camera with it (`limb-plainwall`:
    # ATE 15.4 cm at 0, 0.03 at 0.3; depth alone 0.05); at 0.5 a wall 40 % textured was left to
    # depth (`wall-slide` so altered: ATE 17.1 cm, 0.03 at 0.3).
    colour_pose_min_cover: float = 0.3
    # Motion beyond the depth term's reach (the DeepDeform shirt pair: 20 cm between its two
    # frames): when the colour pairs lie farther than this from where the last warp and the
    # pose put them (median), a first solve led by them (at lead_feature_weight, with the plain
    # squared regulariser, which carries their motion to the nodes between them) is the default
    # solve's start.
    lead_motion_m: float = 0.015
    lead_feature_weight: float = 100.0
    # Each node the last solve saw move (released, with depth pairs) starts the frame moved on
    # by this share of its last step (prediction.py: constant velocity, its position only; 0:
    # none) if it is longer than this many sigma of the depth noise there or the pairs' reach.
    predict_node_motion: float = 1.0
    predict_min_step_sigmas: float = 2.0

    CHOICES = {"camera": CAMERAS}
    UNIT = {"released_rigid_weight", "min_still_share", "predict_node_motion", "colour_pose_min_cover"}
    ZERO_OK = UNIT | {"predict_min_step_sigmas"}


@dataclass(frozen=True)
class SurfelSet:
    """Model points the data term uses: reference positions, normals and their skinning."""
    positions: np.ndarray
    normals: np.ndarray
    knn: np.ndarray
    weights: np.ndarray


def warped_matches(matches: AnchoredMatches, surfels: SurfelSet, field: WarpField) -> np.ndarray:
    """(n, 3) world: each colour match's reference point where `field` puts it, skinned as its
    surfel (what rigid ICP's colour pairs and the pairs-led start compare with the frame)."""
    i = matches.index
    return warp(matches.ref_points, None, surfels.knn[i], surfels.weights[i], field)[0]


@dataclass(frozen=True)
class TrackingCounts:
    """What the tracker did in one frame, as metrics.json lists it (None: not applicable)."""
    correspondences: int                      # depth pairs of the non-rigid solve, at its result
    data_rmse_m: float
    rigid_rmse_m: float
    rigid_iterations: int
    rigid_degenerate_directions: int          # directions rigid ICP did not move the camera along
    silhouette_points: int                    # model points the camera saw through (free space)
    released_nodes: int | None = None         # nodes free of their rest anchors
    unsupported_fraction: float | None = None
    unexplained_fraction: float | None = None
    # The silent fallbacks: steps PCG did not converge on (solved by sparse LU), and a frame
    # whose rigid ICP found too few pairs (the pose kept from the frame before).
    lu_fallbacks: int = 0
    rigid_pose_kept: bool = False
    feature_matches: int | None = None        # colour features in the solve (None: no colour)


class Tracker:
    """Camera pose and warp field from frame to frame (holds the pose and its last motion)."""

    def __init__(self, intrinsics: Intrinsics, params: TrackingParams = TrackingParams()):
        self.intrinsics, self.params = intrinsics, params
        self.T_camera_to_world = np.eye(4)
        self._camera_velocity = np.eye(4)     # previous frame's camera motion, T_prev^-1 T_now
        self.tree: Hierarchy | None = None    # the deformation tree of the last solve, if enabled
        self._tree_nodes: np.ndarray | None = None
        self.anchors: NodeAnchors | None = None   # of the last solved field, if anchors are on
        self._T_previous = self._T_guess = np.eye(4)
        self._scene_motion: np.ndarray | None = None   # ICP's motion when it is not the camera's
        self._held: HeldDirections | None = None       # directions ICP did not move the camera along
        self._camera_moves = params.camera == "moving"  # this frame: still surface to tell its motion
        self._lu_fallbacks = 0                          # this frame's, over every solve
        self._free_space: tuple[CameraObservation, FreeSpace] | None = None
        self._spaces_ahead = FoundAhead()          # FreeSpace by observation, built by `ahead`
        self.colour = ColourMatcher(intrinsics, params.features)
        self._feature_count: int | None = None
        self.motion = NodeMotion(params.predict_node_motion, min_step_sigmas=params.predict_min_step_sigmas,
                                 reach_m=params.nonrigid.distance_gate_m)

    def __getstate__(self) -> dict:
        """A checkpoint's copy (io/checkpoint.py) leaves out the free-space caches: half its
        size, and the next frame builds its own."""
        return self.__dict__ | {"_free_space": None}

    def free_space(self, obs: CameraObservation, T_camera_to_world: np.ndarray) -> FreeSpace:
        """The observation's free space seen from T_camera_to_world, built once per observation
        (by `ahead`, or on the first call) for the frame's solves and the model's carving."""
        if self._free_space is None or self._free_space[0] is not obs:
            early = self._spaces_ahead.get(obs)
            self._free_space = obs, early if early is not None else self._build_free_space(obs)
        return self._free_space[1].moved_to(T_camera_to_world)

    def _build_free_space(self, obs: CameraObservation) -> FreeSpace:
        """At the camera (the pose only places it: free_space moves it to the frame's)."""
        return FreeSpace(obs.depth_m, self.intrinsics, np.eye(4), self.params.nonrigid.silhouette, obs.beyond)

    def stillness(self, knn: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(N,) how still each point is (0-1), given its nodes and weights (N, k) in the last
        solved field: its skinning over the nodes' stillness (NodeAnchors; 1 without anchors;
        nodes born since are still)."""
        node = self._node_stillness()
        return np.ones(len(knn), np.float32) if node is None else point_stillness(knn, weights, node)

    def stillness_map(self, index_map: np.ndarray, knn: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(H, W) stillness of a model map whose pixels show the points `index_map` (-1: none,
        NaN in the map) of the skinning knn/weights."""
        node = self._node_stillness()
        if node is None:
            return np.where(index_map >= 0, np.float32(1.0), np.float32(np.nan))
        return stillness_map(index_map, knn, weights, node)

    def _node_stillness(self) -> np.ndarray | None:
        """(M,) the rest anchors' node stillness; None without anchors (every point still)."""
        return self.anchors.still_weights() if self.anchors is not None and self.params.anchor.weight > 0 else None

    def colour_pairs(self, matches: AnchoredMatches | None, surfels: SurfelSet, field: WarpField
                     ) -> PointPairs | None:
        """The colour matches as rigid ICP's point pairs: each surfel's point where the last
        field puts it (world) and where this frame sees it, weighed by its stillness (as the
        depth it lies on)."""
        p = self.params
        if matches is None or len(matches) == 0 or not p.colour_pose:
            return None
        still = rigid_weight(self.stillness(surfels.knn[matches.index], surfels.weights[matches.index]),
                             p.released_rigid_weight)
        return PointPairs(matches.target_points, warped_matches(matches, surfels, field), matches.weights * still)

    def rigid(self, model_vertex: np.ndarray, model_normal: np.ndarray, obs: CameraObservation,
              stillness: np.ndarray | None = None,
              pairs: PointPairs | None = None) -> RigidResult:
        """Rigid ICP of the observation to world-frame model maps drawn at the current pose.
        With a stillness map (stillness_map), the still surface leads (released_rigid_weight);
        with too little of it in view (min_still_share), or a static camera, the pose is held
        and ICP's motion is kept as the scene's, the non-rigid solve's second start. The pose
        is also held if ICP found too few pairs."""
        p = self.params
        self._T_previous = self.T_camera_to_world
        self._T_guess = self.T_camera_to_world @ self._camera_velocity if p.predict_motion else self.T_camera_to_world
        self._scene_motion, self._lu_fallbacks = None, 0
        weight, share = (None, 1.0) if stillness is None else rigid_weight_map(stillness, p.released_rigid_weight)
        self._held, self._camera_moves = None, p.camera == "moving" and share >= p.min_still_share
        # The colour pairs inform the camera's pose where they cover its still surface; where it
        # is held, ICP's motion is the scene's, only the non-rigid solve's second start, and they
        # are left to that solve.
        use_pairs = pairs is not None and self._camera_moves and (stillness is None or covered_share(
            np.isfinite(stillness) if weight is None else weight,
            self.intrinsics.project(pairs.camera)) >= p.colour_pose_min_cover)
        result = rigid_icp(model_vertex, model_normal, self.T_camera_to_world, obs, self._T_guess, p.rigid,
                           model_weight_map=weight, pairs=pairs if use_pairs else None)
        if not np.isfinite(result.rmse_m):
            self._T_guess = self._T_previous
        elif self._camera_moves:
            self.T_camera_to_world, self._held = result.T_camera_to_world, result.held
        else:
            self._scene_motion = self.T_camera_to_world @ invert(result.T_camera_to_world)
            self._T_guess = self.T_camera_to_world
        return result

    def new_reference(self, obs: CameraObservation, ids: np.ndarray, ref_position: np.ndarray) -> None:
        """The reference frame's colour features on the reference model (colour.py); call with
        each new reference (the first frame, every reinitialisation)."""
        if self.uses_features:
            self.colour.new_reference(obs, self.T_camera_to_world, ids, ref_position)

    @property
    def uses_features(self) -> bool:
        """Whether `features` matches colour (the feature term is on): the model view it reads
        need not draw the model's colour otherwise."""
        return self.params.nonrigid.feature_weight > 0

    def ahead(self, obs: CameraObservation) -> None:
        """The work on `obs` that reads no model, done before its frame on the run's read-ahead
        worker: its free space and its colour work (colour.py)."""
        self._spaces_ahead.put(obs, self._build_free_space(obs))
        if self.uses_features:
            self.colour.ahead(obs)

    def features(self, obs: CameraObservation, model: ModelView | None = None, field: WarpField | None = None,
                 ended: WarpField | None = None) -> AnchoredMatches | None:
        """Colour correspondences of `obs` on the solved surfels (colour.py; `ended`: the field
        before `predicted`), predicted at the last pose; call before `rigid` (which takes them
        with colour_pairs). With no model (the first frame) it only remembers obs. None without
        colour or with the feature term off."""
        self._feature_count = None
        if not self.uses_features:
            return None
        matches = self.colour.matches(obs, model, field, self.T_camera_to_world,
                                      self.T_camera_to_world @ self._camera_velocity, ended)
        self._feature_count = None if matches is None else len(matches)
        return matches

    def nonrigid(self, field: WarpField, surfels: SurfelSet, obs: CameraObservation,
                 matches: AnchoredMatches | None = None) -> tuple[WarpField, NonRigidResult]:
        """Gauss-Newton from `field` at the rigid pose; call after `rigid` (and `features`, whose
        matches it takes). Returns the solved field (not yet factored)."""
        depth = (obs.vertex_map, obs.normal_map, obs.valid, self.intrinsics)
        model = (surfels.positions, surfels.normals, surfels.knn, surfels.weights)
        h = self.params.hierarchy
        solve_field = with_hierarchy(field, self._hierarchy(field), h.keep_graph) if h.enabled else field
        anchor = None
        if self.params.anchor.weight > 0:
            self.anchors = self.anchors.follow(field) if self.anchors is not None else NodeAnchors.at_rest(field)
            anchor = self.anchors.term(self.params.anchor, node_depth_m(field, self.T_camera_to_world),
                                       solve_field.num_nodes, self._held)

        def solve(start: WarpField, T_camera_to_world: np.ndarray, params: NonRigidParams = self.params.nonrigid
                  ) -> tuple[WarpField, NonRigidResult]:
            solved, result = solve_nonrigid(start, *model, *depth, T_camera_to_world, params, anchor,
                                            obs.beyond, self.free_space(obs, T_camera_to_world), matches)
            self._lu_fallbacks += result.lu_fallbacks
            return solved, result

        def fits_better(second: NonRigidResult) -> bool:
            """A second start's fit wins with a lower energy over about as many pairs."""
            return second.energy < result.energy and second.correspondences >= 0.9 * result.correspondences

        if self._pairs_far(field, surfels, matches):
            lead = replace(self.params.nonrigid, feature_weight=self.params.lead_feature_weight, reg_huber_m=0.0)
            solve_field, _ = solve(solve_field, self.T_camera_to_world, lead)
        solved, result = solve(solve_field, self.T_camera_to_world)
        M = self._scene_motion
        if M is not None and (not result.converged or result.correspondences < 0.8 * len(surfels.positions)):
            # The scene's rigid motion by ICP, tried as a second start: a fast object needs it,
            # a surface whose shape travels across it (waves) is better off without.
            moved = field.with_transforms(follow_motion(field.transforms, field.nodes, M))
            moved_solve = with_hierarchy(moved, self._hierarchy(moved), h.keep_graph) if h.enabled else moved
            solved2, result2 = solve(moved_solve, self.T_camera_to_world)
            if fits_better(result2):
                solved, result = solved2, result2
        elif not result.converged and not np.array_equal(self.T_camera_to_world, self._T_guess):
            # Rigid ICP can mistake deformation for camera motion: try the solve from the
            # starting pose too.
            solved2, result2 = solve(solve_field, self._T_guess)
            if fits_better(result2):
                solved, result, self.T_camera_to_world = solved2, result2, self._T_guess
        if result.released is not None:
            self.anchors = self.anchors.release(result.released)
        # The tree's upper levels only regularise; the warp nodes come first.
        return field.with_transforms(solved.transforms[:field.num_nodes]), result

    def predicted(self, field: WarpField, obs: CameraObservation, model: SurfelSet, live: np.ndarray,
                  live_normals: np.ndarray) -> WarpField:
        """`field` with each node the last solve saw move carried on by its last step where the model
        finds the depth of `obs` as well from there (prediction.carry_on: live values warped in place)."""
        start, p = self.motion.predicted(field), self.params.nonrigid
        return field if start is field else carry_on(
            field, start, model.positions, model.normals, model.knn, model.weights, live, live_normals,
            DepthTargets(obs.vertex_map, obs.normal_map, obs.valid, self.intrinsics, self.T_camera_to_world),
            p.distance_gate_m, p.min_normal_cos)

    def _pairs_far(self, field: WarpField, surfels: SurfelSet, matches: AnchoredMatches | None) -> bool:
        """Whether the colour pairs lie, in the median, beyond lead_motion_m of where the field
        and the pose put them."""
        if matches is None or len(matches) == 0 or not self.uses_features:
            return False
        seen = transform_points(self.T_camera_to_world, matches.target_points)
        live = warped_matches(matches, surfels, field)
        return float(np.median(np.linalg.norm(live - seen, axis=1))) > self.params.lead_motion_m

    def counts(self, rigid: RigidResult, nonrigid: NonRigidResult) -> TrackingCounts:
        """The frame's counts, after `factor`."""
        alignment = nonrigid.alignment
        return TrackingCounts(
            nonrigid.correspondences, float(nonrigid.data_rmse_m), float(rigid.rmse_m), rigid.iterations,
            rigid.degenerate_directions, nonrigid.silhouette_points,
            int(self.anchors.released.sum()) if self.anchors is not None else None,
            round(alignment.unsupported_fraction, 5) if alignment is not None else None,
            round(alignment.unexplained_fraction, 5) if alignment is not None else None,
            self._lu_fallbacks, not np.isfinite(rigid.rmse_m), self._feature_count)

    def _hierarchy(self, field: WarpField) -> Hierarchy:
        """The deformation tree over the field's nodes, rebuilt when they change."""
        if self._tree_nodes is not field.nodes:
            h = self.params.hierarchy
            self.tree = build_hierarchy(field.nodes, field.params.node_radius_m, h.levels, h.beta, h.k)
            self._tree_nodes = field.nodes
        return self.tree

    def factor(self, field: WarpField, result: NonRigidResult | None = None) -> WarpField:
        """Move the field's common rigid motion into the pose (if enabled); ends the frame.
        `result` (the solve's) gives the node information the motion is fitted to."""
        p = self.params
        anchors = self.anchors if p.anchor.weight > 0 and self.anchors is not None \
            and self.anchors.nodes is field.nodes else None
        if p.factor_rigid_motion and self._camera_moves:
            information, rest = None, None
            if p.factor_by_support and result is not None and result.node_information is not None:
                information = result.node_information[:field.num_nodes]
                weight = np.trace(information, axis1=1, axis2=2)
                # a fit needs three nodes not on a line; fewer supported: every node alike
                information = information if np.count_nonzero(weight) >= 3 else None
            if anchors is not None and information is not None:
                held = np.where(anchors.released[:, None, None], 0.0, information)
                held_weight = np.trace(held, axis1=1, axis2=2)
                if np.count_nonzero(held_weight) >= 3 and held_weight.sum() >= 0.5 * weight.sum():
                    # The motion that returns the anchored nodes to rest is the camera's; fitted
                    # to all, the moving parts would drag the pose and the anchored nodes along.
                    information, rest = held, field.nodes + anchors.rest[:, :3, 3]
            field, A = factor_rigid_motion(field, information, rest, self._held)
            self.T_camera_to_world = invert(A) @ self.T_camera_to_world
        if anchors is not None:
            self.anchors = anchors.settle(field, node_depth_m(field, self.T_camera_to_world), p.anchor)
        self._camera_velocity = invert(self._T_previous) @ self.T_camera_to_world
        information = None if result is None or result.node_information is None else \
            result.node_information[:field.num_nodes]
        released = None
        if p.anchor.weight > 0:
            released = self.anchors.released if self.anchors is not None and self.anchors.nodes is field.nodes \
                else np.zeros(field.num_nodes, bool)
        self.motion.end_frame(field, carried_nodes(information, released), self.T_camera_to_world)
        return field
