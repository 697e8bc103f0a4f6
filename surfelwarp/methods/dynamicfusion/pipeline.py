"""The DynamicFusion baseline (Newcombe et al. 2015), sharing SurfelWarp's tracker.

The canonical model is a TSDF volume (tsdf.py) in world coordinates; the warp field is the same
node graph, rigid ICP and Gauss-Newton solver as SurfelWarpMethod (SurfelWarp Sec. IX compares
against exactly such a baseline). Per frame, `DynamicFusionMethod.process` runs:

    solver maps of the warped canonical mesh (previous camera) -> rigid ICP -> data points: one
    per covered pixel, taken back to canonical space (Eq. 7) -> non-rigid GN -> grow the volume
    over depth seen outside it -> warp the voxels that can be fused -> projective TSDF fusion
    (Eq. 3-5) -> marching cubes -> extend the warp field to uncovered surface (Sec. 3.4) -> warp
    the mesh.

Blocks of voxels that provably cannot be fused this frame are not warped (voxel_blocks.py).
The mesh extracted after fusion serves three uses: this frame's output (warped by W_t), the
nodes' coverage test, and the next frame's data term (DynamicFusion Sec. 3.3.1 extracts it
before the solve; it is the same mesh, so it is extracted once).
With colour input the voxels also average the colour, with the tsdf's weights, and the mesh
vertices take it from the voxels around them (tsdf.sample_color).
The regulariser can use DynamicFusion's hierarchical deformation tree (tracking.hierarchy,
deform/hierarchy.py), as the shared tracker can for SurfelWarp.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from surfelwarp.deform.warp_field import WarpField, extend, inverse_warp, skin, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert, transform_surfels
from surfelwarp.io.outputs import FrameRecord
from surfelwarp.io.ply import vertex_table
from surfelwarp.methods.dynamicfusion.params import DynamicFusionParams
from surfelwarp.methods.dynamicfusion.tsdf import TSDFVolume, extract_mesh, fuse, sample_color
from surfelwarp.methods.dynamicfusion.voxel_field import VoxelField
from surfelwarp.preprocess import CameraObservation
from surfelwarp.render.mesh_maps import render_mesh_maps
from surfelwarp.render.solver_maps import maps_to_world
from surfelwarp.timing import StageTimer
from surfelwarp.tracking.features import ModelView
from surfelwarp.tracking.tracker import SurfelSet, Tracker


@dataclass(frozen=True)
class VolumeCounts:
    """The volume and its mesh at the end of a frame (metrics.json)."""
    voxels: int
    observed_voxels: int            # with a fusion weight
    voxel_size_m: float | None
    mesh_vertices: int
    mesh_faces: int
    volume_bytes: int


@dataclass(frozen=True)
class UpdateCounts:
    """What one frame's model update did (metrics.json)."""
    new_nodes: int
    fused_voxels: int
    warped_voxels: int
    data_points: int                # model points of the data term
    grown_voxels: int = 0           # voxels added to cover depth seen outside the volume
    outside_volume_full: bool = False   # depth was seen outside, but growing would pass max_voxels


@dataclass
class CanonicalMesh:
    """The zero level set in world coordinates, its skinning and its current live warp."""
    vertices: np.ndarray       # (N, 3) float32
    normals: np.ndarray        # (N, 3) float32
    faces: np.ndarray          # (F, 3) int32
    knn: np.ndarray            # (N, k) int32
    weights: np.ndarray        # (N, k) float32
    live_vertices: np.ndarray  # (N, 3) float32, world
    live_normals: np.ndarray
    colors: np.ndarray | None = None   # (N, 3) float32 RGB from the volume; None without colour

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in vars(self).values() if a is not None)


class DynamicFusionMethod:
    name = "dynamicfusion"

    def __init__(self, intrinsics: Intrinsics, params: DynamicFusionParams = DynamicFusionParams()):
        self.intrinsics, self.params = intrinsics, params
        self.voxels: VoxelField | None = None     # the volume and its voxels' nodes
        self.field: WarpField | None = None
        self.mesh: CanonicalMesh | None = None
        self.tracker = Tracker(intrinsics, params.tracking)
        self.reference_frame = 0
        self.T_reference_camera_to_world = np.eye(4)
        self.has_color: bool | None = None   # the first observation decides (PLYs keep one layout)

    def config(self) -> dict:
        return self.params.to_dict()

    @property
    def T_camera_to_world(self) -> np.ndarray:
        return self.tracker.T_camera_to_world

    @property
    def volume(self) -> TSDFVolume | None:
        return None if self.voxels is None else self.voxels.volume

    @property
    def started(self) -> bool:
        return self.voxels is not None

    def ahead(self, obs: CameraObservation) -> None:
        """The next frame's work that reads no model (its free space and colour features), done
        while this frame is processed: run.py's read-ahead worker calls it."""
        self.tracker.ahead(obs)

    def hold(self, obs: CameraObservation) -> FrameRecord:
        """Too little depth: no tracking, no fusion; the volume, warp field and pose are kept."""
        return replace(self._record(obs, StageTimer()), tracked=False)

    # ------------------------------------------------------------------ one frame
    def process(self, obs: CameraObservation) -> FrameRecord:
        if self.has_color is None:
            self.has_color = obs.color is not None
        if self.volume is None:
            return self.initialise(obs)
        p, timer = self.params, StageTimer()
        mesh = self.mesh

        # Each moving node carried on by its last step (Tracker.predicted): the maps, the colour
        # features and the solve start from there.
        model = (mesh.vertices, mesh.normals, mesh.knn, mesh.weights)
        ended, self.field = self.field, self.tracker.predicted(self.field, obs, SurfelSet(*model), mesh.live_vertices,
                                                               mesh.live_normals)
        timer.lap("motion")

        # Solver maps: the warped canonical mesh at the previous camera pose.
        T_rendered = self.T_camera_to_world.copy()
        maps = render_mesh_maps(*transform_surfels(invert(T_rendered), mesh.live_vertices, mesh.live_normals),
                                mesh.faces, self.intrinsics)
        timer.lap("solver_maps")

        world_vertex, world_normal = maps_to_world(maps, T_rendered)
        surfels = self.predicted_points(maps, T_rendered)
        timer.lap("predict")
        # Colour features and flow of the last frame matched into this one, on the points drawn at them.
        matches = self.tracker.features(obs, self.model_view(maps, world_vertex, surfels), self.field, ended)
        timer.lap("features")
        rigid = self.tracker.rigid(world_vertex, world_normal, obs,
                                   self.tracker.stillness_map(maps.index, mesh.knn, mesh.weights),
                                   self.tracker.colour_pairs(matches, surfels, self.field))
        timer.lap("rigid")
        solved, nonrigid = self.tracker.nonrigid(self.field, surfels, obs, matches)
        self.field = self.tracker.factor(solved, nonrigid)
        timer.lap("nonrigid")

        # The volume grows over depth seen outside it (at the tracked pose).
        T = self.T_camera_to_world
        grown, full = self.voxels.grow(obs.vertex_map[obs.valid] @ T[:3, :3].T + T[:3, 3], self.field)
        timer.lap("grow")

        depth = self._depth(obs)
        ids = self.voxels.fusible(self.field, invert(T), depth, self.intrinsics) if p.cull_voxels else None
        warped = self.voxels.warp(self.field, ids)
        timer.lap("warp")
        weight = self.voxels.fusion_weight if ids is None else self.voxels.fusion_weight[ids]
        fused = fuse(self.volume, warped, weight, invert(T), depth, self.intrinsics, p.tsdf, voxels=ids,
                     color=obs.color)
        del warped, weight
        timer.lap("fusion")

        vertices, faces, normals = extract_mesh(self.volume)
        timer.lap("marching_cubes")

        first_new = self.field.num_nodes
        if len(vertices):
            self.field, first_new = extend(self.field, vertices)
            if self.field.num_nodes > first_new:
                self.voxels.nodes_added(self.field, first_new)
        timer.lap("extend")

        if len(vertices):   # an empty extraction keeps the previous mesh
            self._set_mesh(vertices, normals, faces)
        timer.lap("warp_mesh")

        update = UpdateCounts(self.field.num_nodes - first_new, fused.updated,
                              self.volume.num_voxels if ids is None else len(ids), len(surfels.positions), grown, full)
        return self._record(obs, timer, nonrigid.iterations, nonrigid.energy,
                            (self.tracker.counts(rigid, nonrigid), update))

    def initialise(self, obs: CameraObservation) -> FrameRecord:
        """The volume bounds the first frame's points (plus margin); that frame is fused with the
        identity warp, and the nodes are sampled from the surface marching cubes extracts."""
        p, timer = self.params, StageTimer()
        points = obs.surfels()["position"]
        if len(points) >= p.min_first_points:
            world, _ = transform_surfels(self.T_camera_to_world, points, points)
            volume = TSDFVolume.from_points(world, p.tsdf, color=self.has_color)
            fuse(volume, None, 1.0, invert(self.T_camera_to_world), self._depth(obs), self.intrinsics, p.tsdf,
                 color=obs.color)
            vertices, faces, normals = extract_mesh(volume)
            if len(vertices):
                self.field = WarpField.from_points(vertices, p.warp_field)
                self.voxels = VoxelField(volume, self.field, p)
                self._set_mesh(vertices, normals, faces)
                self.reference_frame = obs.frame_index
                self.T_reference_camera_to_world = self.T_camera_to_world.copy()
                self.tracker.features(obs)       # remembered for the next frame's matches
        timer.lap("initialise")
        return self._record(obs, timer)

    # ------------------------------------------------------------------ parts
    def predicted_points(self, maps, T_camera_to_world: np.ndarray) -> SurfelSet:
        """The data term's model points (DynamicFusion Eq. 7 sums over the predicted image
        domain): one per pixel the warped mesh covers, at the canonical point that pixel shows.
        `maps` were drawn with the camera at T_camera_to_world.

        The render gives each pixel's live surface point and normal and the mesh vertex nearest
        to it; the point is taken back to canonical space by the inverse of the warp at that
        vertex (the warp varies little across one triangle) and skinned like that vertex. One
        point per pixel rather than per vertex gives the same data density as SurfelWarp's
        per-pixel surfels, so the shared tracker's weights (lambda) mean the same for both.
        """
        mesh = self.mesh
        hit = maps.index >= 0
        vertex = maps.index[hit]
        live, live_n = transform_surfels(T_camera_to_world, maps.vertex[hit], maps.normal[hit])
        knn, weights = mesh.knn[vertex], mesh.weights[vertex]
        ref, ref_n = inverse_warp(live, live_n, knn, weights, self.field)
        return SurfelSet(ref, ref_n, knn, weights)

    def model_view(self, maps, world_vertex: np.ndarray, points: SurfelSet) -> ModelView:
        """The predicted points (predicted_points, in pixel order) as the feature stage reads the
        model; world_vertex is the maps' vertex map in world (maps_to_world). The mesh is
        extracted anew each frame, so no point lives on: there are no ids and no
        reference-frame features, only the last frame's."""
        hit = maps.index >= 0
        index_map = np.full(maps.index.shape, -1, np.int64)
        index_map[hit] = np.arange(int(hit.sum()))
        return ModelView(index_map, index_map[hit], world_vertex[hit], None, points.knn, points.weights,
                         ref_position=points.positions)

    def _depth(self, obs: CameraObservation) -> np.ndarray:
        """The depth the tracker used: filtered, only where the observation is valid."""
        return np.where(obs.valid, obs.depth_m, 0).astype(np.float32)

    def _set_mesh(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
        wf = self.field.params
        knn, weights = skin(vertices, self.field.nodes, wf.k_skin, self.field.sigma_m)
        live, live_n = warp(vertices, normals, knn, weights, self.field)
        colors = sample_color(self.volume, vertices) if self.volume.color is not None else None
        self.mesh = CanonicalMesh(vertices, normals, faces, knn, weights, live, live_n, colors)

    def model_bytes(self) -> int:
        return sum(self.model_parts_bytes().values())

    def model_parts_bytes(self) -> dict[str, int]:
        """Memory held by the model: the volume, the voxel node field (k-NN, skinning and fusion
        weights, centres, block node sets), the canonical mesh and the warp field."""
        if self.volume is None:
            return {"volume": 0, "voxel_field": 0, "mesh": 0, "warp_field": 0}
        f = self.field
        return {"volume": self.volume.nbytes, "voxel_field": self.voxels.nbytes,
                "mesh": self.mesh.nbytes,
                "warp_field": f.nodes.nbytes + f.transforms.nbytes + f.graph.nbytes}

    def _record(self, obs: CameraObservation, timer: StageTimer, gauss_newton_iterations: int = 0,
                energy: float = 0.0, details: tuple = ()) -> FrameRecord:
        ready = self.volume is not None
        sizes = self.model_parts_bytes()
        volume = VolumeCounts(self.volume.num_voxels if ready else 0,
                              int(np.count_nonzero(self.volume.weight)) if ready else 0,
                              self.volume.voxel_size if ready else None, len(self.mesh.vertices) if ready else 0,
                              len(self.mesh.faces) if ready else 0, sizes["volume"])
        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds=timer.seconds,
                           nodes=self.field.num_nodes if ready else 0,
                           gauss_newton_iterations=gauss_newton_iterations, energy=energy,
                           model_bytes=sum(sizes.values()), details=(volume,) + details)

    def finish(self, out_dir, frames) -> None:
        """Nothing beyond the common outputs."""

    # ------------------------------------------------------------------ outputs
    def live_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """The warped canonical mesh in this frame's camera; ref_* = canonical positions in the
        reference frame's camera."""
        if self.mesh is None:
            empty = np.zeros((0, 3), np.float32)
            table = vertex_table(empty, empty, empty, color=empty if self.has_color else None)
            return table, np.zeros((0, 3), np.int32)
        m = self.mesh
        live, live_n = transform_surfels(invert(self.T_camera_to_world), m.live_vertices, m.live_normals)
        ref, _ = transform_surfels(invert(self.T_reference_camera_to_world), m.vertices, m.normals)
        return vertex_table(live, live_n, ref, color=m.colors), m.faces

    def model_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """The canonical mesh in the reference frame's camera."""
        if self.mesh is None:
            return self.live_vertices()
        m = self.mesh
        ref, ref_n = transform_surfels(invert(self.T_reference_camera_to_world), m.vertices, m.normals)
        return vertex_table(ref, ref_n, ref, color=m.colors), m.faces
