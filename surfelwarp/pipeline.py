"""SurfelWarp, one frame at a time (Gao & Tedrake 2018, Fig. 1).

`SurfelWarpMethod.process` is the whole per-frame pipeline, top to bottom:
draw solver maps -> rigid ICP -> non-rigid Gauss-Newton -> forward warp -> (fusion stages).
With `fusion=False` the first frame's surfels are a fixed template tracked through the sequence.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from .camera import Intrinsics
from .gl.solver_maps import SolverMaps, render_solver_maps
from .observation import CameraObservation
from .outputs import FrameRecord
from .ply import vertex_table
from .se3 import invert, transform_points
from .surfels import SurfelModel
from .timing import StageTimer
from .tracking import SurfelSet, Tracker, TrackingParams
from .warp_field import WarpField, WarpFieldParams, skin, warp


@dataclass(frozen=True)
class SurfelWarpParams:
    warp_field: WarpFieldParams = field(default_factory=WarpFieldParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)
    stable_confidence: float = 10.0   # delta_stable: surfels drawn into the solver maps (Table 1)
    recent_frames: int = 2            # delta_recent: ... or observed this recently (Table 1)

    def to_dict(self) -> dict:
        return asdict(self)


def transform_surfels(T: np.ndarray, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions and normals moved by the rigid transform T, as float32."""
    R = T[:3, :3].astype(np.float32)
    return transform_points(T, points).astype(np.float32), (normals @ R.T).astype(np.float32)


def maps_to_world(maps: SolverMaps, T_camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solver maps in world coordinates, zero where no surfel was drawn (as rigid ICP expects)."""
    empty = maps.index < 0
    R = T_camera_to_world[:3, :3].astype(np.float32)
    vertex = maps.vertex @ R.T + T_camera_to_world[:3, 3].astype(np.float32)
    normal = maps.normal @ R.T
    vertex[empty] = 0
    normal[empty] = 0
    return vertex, normal


class SurfelWarpMethod:
    name = "surfelwarp"

    def __init__(self, intrinsics: Intrinsics, params: SurfelWarpParams = SurfelWarpParams(),
                 fusion: bool = True):
        if fusion:
            raise NotImplementedError("surfel fusion (SurfelWarp Sec. VI) is not implemented yet")
        self.intrinsics, self.params, self.fusion = intrinsics, params, fusion
        self.model: SurfelModel | None = None
        self.field: WarpField | None = None
        self.tracker = Tracker(intrinsics, params.tracking)
        self.reference_frame = 0
        self.T_reference_camera_to_world = np.eye(4)
        self._next_id = 0

    def config(self) -> dict:
        return self.params.to_dict() | {"fusion": self.fusion}

    @property
    def T_camera_to_world(self) -> np.ndarray:
        return self.tracker.T_camera_to_world

    # ------------------------------------------------------------------ one frame
    def process(self, obs: CameraObservation) -> FrameRecord:
        if self.model is None:
            return self.initialise(obs)
        p, timer = self.params, StageTimer()
        m = self.model

        # Solver maps: the drawn surfels at the previous camera pose.
        T_world_to_camera = invert(self.T_camera_to_world)
        drawn = None if not self.fusion else np.flatnonzero(
            (m.confidence >= p.stable_confidence) | (obs.time - m.t_observed <= p.recent_frames))
        maps = render_solver_maps(*transform_surfels(T_world_to_camera, m.live_position, m.live_normal),
                                  m.radius, self.intrinsics, indices=drawn)
        timer.lap("solver_maps")

        # Rigid alignment of the observation to the rendered model.
        rigid = self.tracker.rigid(*maps_to_world(maps, self.T_camera_to_world), obs)
        timer.lap("rigid")

        # Non-rigid warp field on the visible surfels.
        visible = np.unique(maps.index[maps.index >= 0])
        surfels = SurfelSet(m.ref_position[visible], m.ref_normal[visible], m.knn[visible], m.weights[visible])
        field, nonrigid = self.tracker.nonrigid(self.field, surfels, obs)
        self.field = self.tracker.factor(field)
        timer.lap("nonrigid")

        # Forward warp of the whole reference model.
        m.live_position, m.live_normal = warp(m.ref_position, m.ref_normal, m.knn, m.weights, self.field)
        timer.lap("warp")

        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds=timer.seconds,
                           surfels=len(m), nodes=self.field.num_nodes,
                           gauss_newton_iterations=nonrigid.iterations, energy=nonrigid.energy,
                           extra={"correspondences": nonrigid.correspondences,
                                  "rigid_rmse_m": float(rigid.rmse_m), "rigid_iterations": rigid.iterations})

    def initialise(self, obs: CameraObservation) -> FrameRecord:
        """Sec. VI-E: the first frame's depth surfels become S_ref = S_live; nodes sub-sampled from them."""
        timer = StageTimer()
        s = obs.surfels()
        position, normal = transform_surfels(self.T_camera_to_world, s["position"], s["normal"])
        self.model = SurfelModel.from_points(position, normal, s["radius"], s["confidence"], obs.time,
                                             self._next_id, self.params.warp_field.k_skin)
        self._next_id += len(self.model)
        self.field = WarpField.from_points(self.model.ref_position, self.params.warp_field)
        self.model.knn, self.model.weights = skin(self.model.ref_position, self.field.nodes,
                                                  self.params.warp_field.k_skin, self.field.sigma_m)
        self.reference_frame = obs.frame_index
        self.T_reference_camera_to_world = self.T_camera_to_world.copy()
        timer.lap("initialise")
        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds=timer.seconds,
                           surfels=len(self.model), nodes=self.field.num_nodes)

    # ------------------------------------------------------------------ outputs
    def live_vertices(self) -> tuple[np.ndarray, None]:
        """Live surfels in this frame's camera; ref_* in the reference frame's camera."""
        m = self.model
        position, normal = transform_surfels(invert(self.T_camera_to_world), m.live_position, m.live_normal)
        ref, _ = transform_surfels(invert(self.T_reference_camera_to_world), m.ref_position, m.ref_normal)
        return vertex_table(position, normal, ref, m.radius, m.confidence, m.ids), None

    def model_vertices(self) -> tuple[np.ndarray, None]:
        """The reference model in the reference frame's camera."""
        m = self.model
        ref, ref_normal = transform_surfels(invert(self.T_reference_camera_to_world), m.ref_position, m.ref_normal)
        return vertex_table(ref, ref_normal, ref, m.radius, m.confidence, m.ids), None
