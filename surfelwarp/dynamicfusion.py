"""The DynamicFusion baseline (Newcombe et al. 2015), sharing SurfelWarp's tracker.

The canonical model is a TSDF volume (tsdf.py) in world coordinates; the warp field is the same
node graph, rigid ICP and Gauss-Newton solver as SurfelWarpMethod (SurfelWarp Sec. IX compares
against exactly such a baseline). Per frame, `DynamicFusionMethod.process` runs:

    solver maps of the warped canonical mesh (previous camera) -> rigid ICP -> non-rigid GN on
    the visible mesh vertices -> warp every voxel centre -> projective TSDF fusion (Eq. 3-5)
    -> marching cubes -> extend the warp field to uncovered surface (Sec. 3.4) -> warp the mesh.

The mesh extracted after fusion serves three uses: this frame's output (warped by W_t), the
nodes' coverage test, and the next frame's data term (DynamicFusion Sec. 3.3.1 extracts it
before the solve; it is the same mesh, so it is extracted once).
Optionally the regulariser uses DynamicFusion's hierarchical deformation tree (Sec. 3.3.2/3.4)
instead of the k-nearest-node graph.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from pykdtree.kdtree import KDTree

from .camera import Intrinsics
from .dual_quaternion import dq_to_transform
from .gl.mesh_maps import render_mesh_maps
from .observation import CameraObservation
from .outputs import FrameRecord
from .pipeline import maps_to_world, transform_surfels
from .ply import vertex_table
from .se3 import invert
from .timing import StageTimer
from .tracking import SurfelSet, Tracker, TrackingParams
from .tsdf import TSDFParams, TSDFVolume, extract_mesh, fuse, node_distance_weight
from .warp_field import (WarpField, WarpFieldParams, blend, extend, sample_nodes, skin, to_local,
                         update_skinning, warp)


@dataclass(frozen=True)
class DynamicFusionParams:
    tsdf: TSDFParams = field(default_factory=TSDFParams)
    # node_radius_m is DynamicFusion's decimation density epsilon (25 mm, Sec. 4).
    warp_field: WarpFieldParams = field(default_factory=WarpFieldParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)   # the same tracker as SurfelWarp
    hierarchical_graph: bool = False  # regularise through the deformation tree (Sec. 3.3.2)
    hierarchy_levels: int = 4         # L, counting the warp nodes as level 0 (Sec. 4)
    hierarchy_beta: float = 4.0       # level l is decimated at epsilon * beta^l
    hierarchy_k: int = 4              # edges from each node to its k nearest of the next level
    min_first_points: int = 500       # the model starts at the first frame with this many valid pixels
    voxel_chunk: int = 1 << 18        # voxels per warp / skinning batch (bounds temporaries)

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------- deformation tree

@dataclass(frozen=True)
class Hierarchy:
    """Regularisation nodes above the warp nodes: levels[l] = global indices of level l's nodes
    in `nodes` (level 0 = the warp nodes, first). Each node of level l links to its k nearest
    nodes of level l+1 (siblings are not linked); `graph` stores every link at its coarse end,
    as solve_nonrigid's graph expects: row j lists the finer nodes i linked to j, so the edge's
    residual is T_i p_j - T_j p_j, DynamicFusion Eq. 8 with j in E(i). Unused slots hold j."""
    nodes: np.ndarray       # (M_total, 3) float32
    graph: np.ndarray       # (M_total, max in-degree) int32
    levels: tuple[np.ndarray, ...]

    @property
    def num_warp_nodes(self) -> int:
        return len(self.levels[0])


def build_hierarchy(warp_nodes: np.ndarray, epsilon_m: float, levels: int, beta: float, k: int) -> Hierarchy:
    """DynamicFusion Sec. 3.4: level l subsamples level l-1 at radius epsilon * beta^l (stopping
    early once a level has a single node); each node links to its k nearest nodes of level l+1."""
    layers = [np.asarray(warp_nodes, np.float32).reshape(-1, 3)]
    for level in range(1, levels):
        if len(layers[-1]) <= 1:
            break
        layers.append(sample_nodes(layers[-1], epsilon_m * beta ** level))
    nodes = np.concatenate(layers)
    starts = np.cumsum([0] + [len(a) for a in layers])
    fine, coarse = [], []
    for level in range(len(layers) - 1):
        j = min(k, len(layers[level + 1]))
        _, idx = KDTree(layers[level + 1]).query(layers[level], k=j)
        fine.append(np.repeat(np.arange(starts[level], starts[level + 1]), j))
        coarse.append(idx.reshape(-1).astype(np.int64) + starts[level + 1])
    fine = np.concatenate(fine) if fine else np.zeros(0, np.int64)
    coarse = np.concatenate(coarse) if coarse else np.zeros(0, np.int64)
    # Links grouped by their coarse end; each gets a slot number within its group.
    order = np.argsort(coarse, kind="stable")
    fine, coarse = fine[order], coarse[order]
    degree = np.bincount(coarse, minlength=len(nodes))
    slot = np.arange(len(coarse)) - np.repeat(np.cumsum(degree) - degree, degree)
    graph = np.repeat(np.arange(len(nodes), dtype=np.int32)[:, None], max(int(degree.max(initial=0)), 1), axis=1)
    graph[coarse, slot] = fine
    return Hierarchy(nodes, graph, tuple(np.arange(starts[i], starts[i + 1]) for i in range(len(layers))))


def warp_transforms_at(field: WarpField, points: np.ndarray) -> np.ndarray:
    """(n, 4, 4) node-local transforms at `points` equal to the current warp there (DQB)."""
    knn, w = skin(points, field.nodes, field.params.k_skin, field.sigma_m)
    return to_local(dq_to_transform(blend(knn, w, field)), points)


def with_hierarchy(field: WarpField, tree: Hierarchy) -> WarpField:
    """The warp field plus the regularisation nodes (transforms from the current warp) and the
    tree's edges: solve_nonrigid optimises them all, the data term only touches level 0."""
    extra = tree.nodes[tree.num_warp_nodes:]
    transforms = np.concatenate([field.transforms, warp_transforms_at(field, extra)]) if len(extra) \
        else field.transforms
    return WarpField(tree.nodes, transforms, tree.graph, field.params)


# ---------------------------------------------------------------- the method

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

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in vars(self).values())


class DynamicFusionMethod:
    name = "dynamicfusion"

    def __init__(self, intrinsics: Intrinsics, params: DynamicFusionParams = DynamicFusionParams()):
        self.intrinsics, self.params = intrinsics, params
        self.volume: TSDFVolume | None = None
        self.field: WarpField | None = None
        self.mesh: CanonicalMesh | None = None
        self.tree: Hierarchy | None = None
        self.voxel_knn = self.voxel_weights = self.voxel_fusion_weight = None
        self.tracker = Tracker(intrinsics, params.tracking)
        self.reference_frame = 0
        self.T_reference_camera_to_world = np.eye(4)

    def config(self) -> dict:
        return self.params.to_dict()

    @property
    def T_camera_to_world(self) -> np.ndarray:
        return self.tracker.T_camera_to_world

    # ------------------------------------------------------------------ one frame
    def process(self, obs: CameraObservation) -> FrameRecord:
        if self.volume is None:
            return self.initialise(obs)
        p, timer = self.params, StageTimer()
        mesh = self.mesh

        # Solver maps: the warped canonical mesh at the previous camera pose.
        T_world_to_camera = invert(self.T_camera_to_world)
        maps = render_mesh_maps(*transform_surfels(T_world_to_camera, mesh.live_vertices, mesh.live_normals),
                                mesh.faces, self.intrinsics)
        timer.lap("solver_maps")

        rigid = self.tracker.rigid(*maps_to_world(maps, self.T_camera_to_world), obs)
        timer.lap("rigid")

        visible = np.unique(maps.index[maps.index >= 0])
        solve_field = self.field if self.tree is None else with_hierarchy(self.field, self.tree)
        surfels = SurfelSet(mesh.vertices[visible], mesh.normals[visible], mesh.knn[visible], mesh.weights[visible])
        solved, nonrigid = self.tracker.nonrigid(solve_field, surfels, obs)
        # The deformation tree's upper levels only regularise; the warp nodes are the first ones.
        self.field = self.tracker.factor(self.field.with_transforms(solved.transforms[:self.field.num_nodes]))
        timer.lap("nonrigid")

        warped = self.warp_voxels()
        timer.lap("warp")
        fused = fuse(self.volume, warped, self.voxel_fusion_weight, invert(self.T_camera_to_world),
                     self._depth(obs), self.intrinsics, p.tsdf)
        del warped
        timer.lap("fusion")

        vertices, faces, normals = extract_mesh(self.volume)
        timer.lap("marching_cubes")

        first_new = self.field.num_nodes
        if len(vertices):
            self.field, first_new = extend(self.field, vertices)
            if self.field.num_nodes > first_new:
                self._update_voxel_skinning(first_new)
        timer.lap("extend")

        if len(vertices):   # an empty extraction keeps the previous mesh
            self._set_mesh(vertices, normals, faces)
        timer.lap("warp_mesh")

        return self._record(obs, timer, gauss_newton_iterations=nonrigid.iterations, energy=nonrigid.energy,
                            extra={"new_nodes": self.field.num_nodes - first_new, "fused_voxels": fused.updated,
                                   "visible_vertices": len(visible), "correspondences": nonrigid.correspondences,
                                   "rigid_rmse_m": float(rigid.rmse_m), "rigid_iterations": rigid.iterations})

    def initialise(self, obs: CameraObservation) -> FrameRecord:
        """The volume bounds the first frame's points (plus margin); that frame is fused with the
        identity warp, and the nodes are sampled from the surface marching cubes extracts."""
        p, timer = self.params, StageTimer()
        points = obs.surfels()["position"]
        if len(points) >= p.min_first_points:
            world, _ = transform_surfels(self.T_camera_to_world, points, points)
            volume = TSDFVolume.from_points(world, p.tsdf)
            fuse(volume, None, 1.0, invert(self.T_camera_to_world), self._depth(obs), self.intrinsics, p.tsdf)
            vertices, faces, normals = extract_mesh(volume)
            if len(vertices):
                self.volume = volume
                self.field = WarpField.from_points(vertices, p.warp_field)
                self.voxel_knn, self.voxel_weights = self._skin_voxels()
                self._update_fusion_weights()
                self._update_tree()
                self._set_mesh(vertices, normals, faces)
                self.reference_frame = obs.frame_index
                self.T_reference_camera_to_world = self.T_camera_to_world.copy()
        timer.lap("initialise")
        return self._record(obs, timer, extra={})

    # ------------------------------------------------------------------ parts
    def _depth(self, obs: CameraObservation) -> np.ndarray:
        """The depth the tracker used: filtered, only where the observation is valid."""
        return np.where(obs.valid, obs.depth_m, 0).astype(np.float32)

    def _chunks(self):
        n, step = self.volume.num_voxels, self.params.voxel_chunk
        for start in range(0, n, step):
            stop = min(start + step, n)
            yield start, stop, self.volume.voxel_centres(start, stop)

    def _skin_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """The discretised k-nearest-node field (DynamicFusion Sec. 3.3.3) at the voxel centres."""
        k = self.params.warp_field.k_skin
        knn = np.empty((self.volume.num_voxels, k), np.int32)
        weights = np.empty((self.volume.num_voxels, k), np.float32)
        for start, stop, centres in self._chunks():
            knn[start:stop], weights[start:stop] = skin(centres, self.field.nodes, k, self.field.sigma_m)
        return knn, weights

    def _update_voxel_skinning(self, first_new: int) -> None:
        """Skinning and fusion weights after nodes first_new.. were added (DynamicFusion Sec. 3.4).

        A voxel's k nearest nodes change only if a new node is nearer than its current k-th
        one, so only those voxels go through update_skinning (near the new nodes: a few %).
        """
        field, k = self.field, self.params.warp_field.k_skin
        tree = KDTree(field.nodes[first_new:])
        for start, stop, centres in self._chunks():
            if first_new < k:   # padded slots: the k-th slot is not the k-th nearest node
                hit = np.arange(stop - start)
            else:
                kth = field.nodes[self.voxel_knn[start:stop, -1]] - centres
                d_new, _ = tree.query(centres, k=1)
                hit = np.flatnonzero(d_new.reshape(-1) ** 2 < np.einsum("ij,ij->i", kth, kth))
            if len(hit) == 0:
                continue
            g = hit + start
            self.voxel_knn[g], self.voxel_weights[g] = update_skinning(
                self.voxel_knn[g], self.voxel_weights[g], centres[hit], field, first_new)
            self.voxel_fusion_weight[g] = node_distance_weight(
                centres[hit], field.nodes, self.voxel_knn[g], self.params.warp_field.node_radius_m)
        self._update_tree()

    def _update_fusion_weights(self) -> None:
        """w(x) of Sec. 3.2, from the canonical nodes only: it changes only when nodes are added."""
        w = np.empty(self.volume.num_voxels, np.float32)
        for start, stop, centres in self._chunks():
            w[start:stop] = node_distance_weight(centres, self.field.nodes, self.voxel_knn[start:stop],
                                                 self.params.warp_field.node_radius_m)
        self.voxel_fusion_weight = w

    def _update_tree(self) -> None:
        p = self.params
        if p.hierarchical_graph:
            self.tree = build_hierarchy(self.field.nodes, p.warp_field.node_radius_m, p.hierarchy_levels,
                                        p.hierarchy_beta, p.hierarchy_k)

    def warp_voxels(self) -> np.ndarray:
        """(V, 3) float32 voxel centres moved by the warp field W (world), flat volume order."""
        out = np.empty((self.volume.num_voxels, 3), np.float32)
        for start, stop, centres in self._chunks():
            out[start:stop], _ = warp(centres, None, self.voxel_knn[start:stop], self.voxel_weights[start:stop],
                                      self.field)
        return out

    def _set_mesh(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
        wf = self.field.params
        knn, weights = skin(vertices, self.field.nodes, wf.k_skin, self.field.sigma_m)
        live, live_n = warp(vertices, normals, knn, weights, self.field)
        self.mesh = CanonicalMesh(vertices, normals, faces, knn, weights, live, live_n)

    def model_bytes(self) -> dict[str, int]:
        """Memory held by the model: the volume, the voxel node field (k-NN, skinning and fusion
        weights), the canonical mesh and the warp field."""
        if self.volume is None:
            return {"volume": 0, "voxel_field": 0, "mesh": 0, "warp_field": 0}
        f = self.field
        return {"volume": self.volume.nbytes,
                "voxel_field": self.voxel_knn.nbytes + self.voxel_weights.nbytes + self.voxel_fusion_weight.nbytes,
                "mesh": self.mesh.nbytes,
                "warp_field": f.nodes.nbytes + f.transforms.nbytes + f.graph.nbytes}

    def _record(self, obs: CameraObservation, timer: StageTimer, gauss_newton_iterations: int = 0,
                energy: float = 0.0, extra: dict | None = None) -> FrameRecord:
        ready = self.volume is not None
        sizes = self.model_bytes()
        counts = {"voxels": self.volume.num_voxels if ready else 0,
                  "observed_voxels": int(np.count_nonzero(self.volume.weight)) if ready else 0,
                  "voxel_size_m": self.volume.voxel_size if ready else None,
                  "mesh_vertices": len(self.mesh.vertices) if ready else 0,
                  "mesh_faces": len(self.mesh.faces) if ready else 0,
                  "model_bytes": sum(sizes.values()), "volume_bytes": sizes["volume"]}
        return FrameRecord(frame=obs.frame_index, reference_frame=self.reference_frame,
                           camera_to_world=self.T_camera_to_world.copy(), seconds=timer.seconds,
                           nodes=self.field.num_nodes if ready else 0,
                           gauss_newton_iterations=gauss_newton_iterations, energy=energy,
                           extra=counts | (extra or {}))

    # ------------------------------------------------------------------ outputs
    def live_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """The warped canonical mesh in this frame's camera; ref_* = canonical positions in the
        reference frame's camera."""
        if self.mesh is None:
            empty = np.zeros((0, 3), np.float32)
            return vertex_table(empty, empty, empty), np.zeros((0, 3), np.int32)
        m = self.mesh
        live, live_n = transform_surfels(invert(self.T_camera_to_world), m.live_vertices, m.live_normals)
        ref, _ = transform_surfels(invert(self.T_reference_camera_to_world), m.vertices, m.normals)
        return vertex_table(live, live_n, ref), m.faces

    def model_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """The canonical mesh in the reference frame's camera."""
        if self.mesh is None:
            return self.live_vertices()
        m = self.mesh
        ref, ref_n = transform_surfels(invert(self.T_reference_camera_to_world), m.vertices, m.normals)
        return vertex_table(ref, ref_n, ref), m.faces
