"""SurfelWarp, one frame at a time (Gao & Tedrake 2018, Fig. 1).

`SurfelWarpMethod.process` is the whole per-frame pipeline, top to bottom: draw solver maps ->
rigid ICP -> colour features put on the model -> non-rigid Gauss-Newton -> forward warp (Sec. VII)
-> index map at the new pose -> fuse depth into live surfels (VI-A) -> skin, reject and append unmatched depth surfels (VI-B..D)
-> remove unstable and redundant surfels (VI-D) -> inverse warp of the fused surfels to S_ref ->
extend the warp field over the appended ones (VI-D) -> reinitialise when tracking struggles (VI-F).
With `fusion=False` the first frame's surfels are a fixed template tracked through the sequence.

All positions are in world coordinates (the first frame's camera); ref_* are written in the
camera of the reference frame (the first frame, or the last reinitialisation).
"""
from __future__ import annotations

import io
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

from surfelwarp.deform.warp_field import WarpField, extend, inverse_warp, skin, update_skinning, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, transform_surfels
from surfelwarp.io.outputs import FrameRecord
from surfelwarp.io.ply import vertex_table, write_atomic
from surfelwarp.methods.surfelwarp.appending import append_candidates
from surfelwarp.methods.surfelwarp.fusion import find_correspondences, fuse, removal_mask, unmatched_depth_pixels
from surfelwarp.methods.surfelwarp.params import SurfelWarpParams
from surfelwarp.methods.surfelwarp.reinit import ReinitTrigger, unsupported_mask
from surfelwarp.methods.surfelwarp.surfels import SurfelModel
from surfelwarp.preprocess import CameraObservation
from surfelwarp.render.colour_map import colour_map
from surfelwarp.render.index_map import render_index_map
from surfelwarp.render.solver_maps import drawn_rows, render_solver_maps
from surfelwarp.timing import StageTimer
from surfelwarp.tracking.features import ModelView
from surfelwarp.tracking.tracker import SurfelSet, Tracker

__all__ = ["SurfelWarpMethod", "SurfelWarpParams", "plot_counts"]


@dataclass(frozen=True)
class ModelUpdateCounts:
    """What fusion, appending, removal and reinitialisation did in one frame (metrics.json)."""
    fused: int                     # depth pixels fused into live surfels
    appended: int
    removed: int                   # unstable, redundant or carved
    carved: int                    # seen through by the camera (free space)
    append_candidates: int
    rejected_weight: int           # candidates far from every node
    rejected_compressive: int
    new_nodes: int
    reinit_dropped: int | None = None   # surfels dropped by a reinitialisation this frame
    reinit_aborted: bool = False        # the trigger fired but too little was left to rebuild on


class SurfelWarpMethod:
    name = "surfelwarp"

    def __init__(self, intrinsics: Intrinsics, params: SurfelWarpParams = SurfelWarpParams(),
                 fusion: bool = True):
        self.intrinsics, self.params, self.fusion = intrinsics, params, fusion
        self.model: SurfelModel | None = None
        self.field: WarpField | None = None
        self.tracker = Tracker(intrinsics, params.tracking)
        self.trigger = ReinitTrigger(params.reinit)
        self.reference_frame = 0
        self.T_reference_camera_to_world = np.eye(4)
        self._next_id = 0
        self.has_color: bool | None = None   # the first observation decides (PLYs keep one layout)

    def config(self) -> dict:
        return self.params.to_dict() | {"fusion_enabled": self.fusion}   # False: template tracking

    @property
    def T_camera_to_world(self) -> np.ndarray:
        return self.tracker.T_camera_to_world

    @property
    def started(self) -> bool:
        return self.model is not None

    # ------------------------------------------------------------------ one frame
    def process(self, obs: CameraObservation) -> FrameRecord:
        if self.model is None:
            return self.initialise(obs)
        p, timer, now = self.params, StageTimer(), obs.time
        m = self.model

        # Each moving node carried on by its last step (Tracker.predicted): the maps, the colour
        # features and the solve start from there.
        model = (m.ref_position, m.ref_normal, m.knn, m.weights)
        ended, self.field = self.field, self.tracker.predicted(self.field, obs, SurfelSet(*model), m.live_position,
                                                               m.live_normal)
        timer.lap("motion")

        # Solver maps: the drawn surfels (all of a template; else stable, and recent ones where
        # no stable surfel is drawn) at the previous pose; the surfels they show are the solve's.
        drawn = fill = None
        if self.fusion:
            stable = m.confidence >= p.fusion.stable_confidence
            recent = now - m.t_observed <= p.recent_frames
            if p.recent_draw == "fill":
                drawn, fill = np.flatnonzero(stable), np.flatnonzero(recent & ~stable)
            elif p.recent_draw == "fill_all":
                drawn, fill = np.flatnonzero(stable), np.flatnonzero(~stable)
            else:
                drawn = np.flatnonzero(stable | recent)
        maps = render_solver_maps(*transform_surfels(invert(self.T_camera_to_world), m.live_position, m.live_normal),
                                  m.radius, self.intrinsics, indices=drawn, fill_indices=fill,
                                  max_radius_px=p.solver_splat_max_px)
        seen = np.zeros(len(m), bool)
        seen[maps.index[maps.index >= 0]] = True
        visible = np.flatnonzero(seen)
        surfels = SurfelSet(*(np.take(a, visible, axis=0) for a in (m.ref_position, m.ref_normal, m.knn, m.weights)))
        timer.lap("solver_maps")

        # Colour features of the last frame matched into this one, on the visible surfels drawn
        # at them.
        matches = self.tracker.features(obs, self._model_view(maps, visible), self.field, ended)
        timer.lap("features")

        # Rigid alignment of the observation to the rendered model (and the colour pairs), led
        # by its still parts.
        rigid = self.tracker.rigid(*drawn_rows(maps.index, m.live_position, m.live_normal), obs,
                                   self.tracker.stillness_map(maps.index, m.knn, m.weights),
                                   self.tracker.colour_pairs(matches, surfels, self.field))
        timer.lap("rigid")

        # Non-rigid warp field on the visible surfels; its common rigid motion goes into the pose.
        field, nonrigid = self.tracker.nonrigid(self.field, surfels, obs, matches)
        self.field = self.tracker.factor(field, nonrigid)
        timer.lap("nonrigid")

        # Forward warp of the whole reference model: S_live = W(S_ref) (Eq. 2).
        m.live_position, m.live_normal = warp(m.ref_position, m.ref_normal, m.knn, m.weights, self.field)
        timer.lap("warp")

        reinitialized, update = False, None
        if self.fusion:
            update = self._fuse_and_update(obs, timer)
            if self.trigger.update(nonrigid.data_rmse_m, update.appended, obs.num_valid, nonrigid.alignment):
                dropped = self.reinitialise(obs)
                update = replace(update, reinit_dropped=dropped, reinit_aborted=dropped is None)
                reinitialized = dropped is not None
                timer.lap("reinit")
        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds=timer.seconds,
                           surfels=len(self.model), nodes=self.field.num_nodes,
                           gauss_newton_iterations=nonrigid.iterations, energy=nonrigid.energy,
                           reinitialized=reinitialized, model_bytes=self.model_bytes(),
                           details=(self.tracker.counts(rigid, nonrigid),) + ((update,) if update else ()))

    def _fuse_and_update(self, obs: CameraObservation, timer: StageTimer) -> ModelUpdateCounts:
        """Sec. VI-A..D on the freshly warped model; returns the frame's counts."""
        p, now, T = self.params, obs.time, self.T_camera_to_world
        m = self.model

        # VI-A: live surfels as points on a 4x4 supersampled index map at the new pose.
        maps = render_index_map(*transform_surfels(invert(T), m.live_position, m.live_normal),
                                self.intrinsics, supersample=p.index_map_supersample)
        timer.lap("fusion_maps")

        # VI-A: each depth pixel fuses into at most one live surfel (Eq. 5).
        corr = find_correspondences(maps, obs, m.confidence, p.fusion)
        m, fused_pixels = fuse(m, T, obs, corr, now, p.fusion)
        fused = np.zeros(len(m), bool)
        fused[corr.surfel_index] = True
        timer.lap("fuse")

        # VI-B..D: unmatched depth surfels, skinned at the live frame, minus far-from-node and
        # compressive ones, inverse-warped with that skinning.
        candidates = unmatched_depth_pixels(obs, fused_pixels, maps if p.fusion.append_only_uncovered else None,
                                            p.fusion)
        added = append_candidates(obs, candidates, T, self.field,
                                  p.warp_field.k_skin, p.append)
        timer.lap("append")

        # VI-D: drop long-unstable surfels and near duplicates on the index map, and the live
        # surfels the camera saw through (free space), then append.
        carved = np.zeros(len(m), bool)
        if np.isfinite(p.fusion.carve_beyond_m):
            carved = self.tracker.free_space(obs, T).seen_through(m.live_position, m.live_normal,
                                                                  p.fusion.carve_beyond_m)
        unstable_or_redundant = removal_mask(m, maps, now, p.fusion, T) | carved
        kept = ~unstable_or_redundant
        m = m.select_then(kept, added.surfels(now, self._next_id))
        self._next_id += len(added)
        fused = np.concatenate([fused[kept], np.zeros(len(added), bool)])
        timer.lap("remove")

        # Sec. IV: the fused live surfels back to the reference frame (Eq. 3).
        fused = np.flatnonzero(fused)
        ref, ref_normal = inverse_warp(*(np.take(a, fused, axis=0) for a in (m.live_position, m.live_normal, m.knn,
                                                                              m.weights)), self.field)
        if p.fusion.reference_along_normal:
            old = np.take(m.ref_position, fused, axis=0)
            ref = old + np.einsum("ij,ij->i", ref - old, ref_normal)[:, None] * ref_normal
        m.ref_position[fused], m.ref_normal[fused] = ref, ref_normal
        timer.lap("inverse_warp")

        # VI-D: nodes for the appended surfels no node covers; the graph is rebuilt, and every
        # surfel's k-NN compared with the new nodes.
        self.field, first_new = extend(self.field, added.ref_position)
        if self.field.num_nodes > first_new:
            m.knn, m.weights = update_skinning(m.knn, m.weights, m.ref_position, self.field, first_new)
        self.model = m
        timer.lap("extend")
        return ModelUpdateCounts(len(corr.surfel_index), len(added), int(unstable_or_redundant.sum()), int(carved.sum()),
                                 added.candidates, added.rejected_weight, added.rejected_compressive,
                                 self.field.num_nodes - first_new)

    def ahead(self, obs: CameraObservation) -> None:
        """The next frame's work that reads no model (its free space and colour features), done
        while this frame is processed: run.py's read-ahead worker calls it."""
        self.tracker.ahead(obs)

    def hold(self, obs: CameraObservation) -> FrameRecord:
        """Too little depth: no tracking, no fusion; the model, warp field and pose are kept."""
        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds={}, surfels=len(self.model),
                           nodes=self.field.num_nodes, model_bytes=self.model_bytes(), tracked=False)

    def initialise(self, obs: CameraObservation) -> FrameRecord:
        """Sec. VI-E: the first frame's depth surfels become S_ref = S_live; nodes sub-sampled from them."""
        timer = StageTimer()
        s = obs.surfels()
        position, normal = transform_surfels(self.T_camera_to_world, s["position"], s["normal"])
        self.has_color = obs.color is not None
        self.model = SurfelModel.from_points(position, normal, s["radius"], s["confidence"], obs.time,
                                             self._next_id, self.params.warp_field.k_skin, s.get("color"))
        self._next_id += len(self.model)
        self._new_reference(obs)
        self.tracker.features(obs)       # remembered for the next frame's matches
        timer.lap("initialise")
        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds=timer.seconds,
                           surfels=len(self.model), nodes=self.field.num_nodes)

    def reinitialise(self, obs: CameraObservation) -> int | None:
        """Sec. VI-F: drop live surfels the depth contradicts, S_ref := S_live, a new warp field.
        Surfels keep their ids, confidences and time stamps. Returns the number dropped; None if
        too little would be left to build a reference on (tracking goes on with what there is)."""
        m = self.model
        drop = unsupported_mask(m.live_position, m.live_normal, self.T_camera_to_world, obs, self.params.reinit)
        if len(m) - drop.sum() < self.params.warp_field.k_skin:
            return None
        m = m.select(~drop)
        m.ref_position, m.ref_normal = m.live_position.copy(), m.live_normal.copy()
        self.model = m
        self._new_reference(obs)
        return int(drop.sum())

    def _model_view(self, maps, visible: np.ndarray) -> ModelView:
        """The model as the feature stage reads it, with its fused colour drawn on the solver maps
        (if the features are matched: drawing it takes ~15 ms a frame on a 640x480 room)."""
        m = self.model
        color = drawn = None
        if self.has_color and self.tracker.uses_features:
            color, drawn = colour_map(maps, m.color_weight > 0, m.color)
        return ModelView(maps.index, visible, m.live_position, m.ids, m.knn, m.weights, maps.vertex, color, drawn,
                         m.ref_position, maps.normal)

    def _new_reference(self, obs: CameraObservation) -> None:
        """Nodes sampled from S_ref with identity transforms, every surfel skinned to them."""
        wp, m = self.params.warp_field, self.model
        self.field = WarpField.from_points(m.ref_position, wp)
        m.knn, m.weights = skin(m.ref_position, self.field.nodes, wp.k_skin, self.field.sigma_m)
        self.reference_frame = obs.frame_index
        self.T_reference_camera_to_world = self.T_camera_to_world.copy()
        self.tracker.new_reference(obs, m.ids, m.ref_position)
        self.trigger.reset()

    # ------------------------------------------------------------------ outputs
    def model_bytes(self) -> int:
        """Every surfel array and the warp field."""
        m, f = self.model, self.field
        total = sum(getattr(m, a.name).nbytes for a in fields(m)) if m is not None else 0
        return int(total + (f.nodes.nbytes + f.transforms.nbytes + f.graph.nbytes if f is not None else 0))

    def live_vertices(self) -> tuple[np.ndarray, None]:
        """Live surfels in this frame's camera; ref_* in the reference frame's camera."""
        m = self.model
        position, normal = transform_surfels(invert(self.T_camera_to_world), m.live_position, m.live_normal)
        ref, _ = transform_surfels(invert(self.T_reference_camera_to_world), m.ref_position, m.ref_normal)
        return vertex_table(position, normal, ref, m.radius, m.confidence, m.ids, self._color()), None

    def model_vertices(self) -> tuple[np.ndarray, None]:
        """The reference model in the reference frame's camera."""
        m = self.model
        ref, ref_normal = transform_surfels(invert(self.T_reference_camera_to_world), m.ref_position, m.ref_normal)
        return vertex_table(ref, ref_normal, ref, m.radius, m.confidence, m.ids, self._color()), None

    def _color(self) -> np.ndarray | None:
        """The surfels' fused colour for the PLYs, only when the input has colour."""
        return self.model.color if self.has_color else None

    def finish(self, out_dir: Path, frames: list[FrameRecord]) -> None:
        """End of a run: OUT/surfels.png (SurfelWarp Fig. 4)."""
        plot_counts(Path(out_dir) / "surfels.png", frames)


def plot_counts(path: Path, frames: list[FrameRecord]) -> None:
    """Surfel and node count per frame, reinitialisations marked; written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r.frame for r in frames]
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(x, [r.surfels for r in frames], color="tab:blue", label="surfels")
    ax.set_xlabel("frame")
    ax.set_ylabel("surfels", color="tab:blue")
    ax.set_ylim(bottom=0)
    nodes = ax.twinx()
    nodes.plot(x, [r.nodes for r in frames], color="tab:orange", label="nodes")
    nodes.set_ylabel("nodes", color="tab:orange")
    nodes.set_ylim(bottom=0)
    for r in frames:
        if r.reinitialized:
            ax.axvline(r.frame, color="tab:red", linestyle=":", linewidth=1)
    ax.set_title("model size per frame" + (" (dotted: reinitialisation)" if any(r.reinitialized for r in frames) else ""))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    write_atomic(path, buf.getvalue())
