"""The DynamicFusion baseline (Newcombe et al. 2015), sharing SurfelWarp's tracker.

The canonical model is a TSDF volume (tsdf.py) in world coordinates; the warp field is the same
node graph, rigid ICP and Gauss-Newton solver as SurfelWarpMethod (SurfelWarp Sec. IX compares
against exactly such a baseline). Per frame, `DynamicFusionMethod.process` runs:

    solver maps of the warped canonical mesh (previous camera) -> rigid ICP -> data points: one
    per covered pixel, taken back to canonical space (Eq. 7) -> non-rigid GN -> warp the voxels
    that can be fused -> projective TSDF fusion (Eq. 3-5) -> marching cubes -> extend the warp
    field to uncovered surface (Sec. 3.4) -> warp the mesh.

Every voxel fusion touches is warped by the full dual quaternion blend; blocks of voxels that
provably cannot be fused this frame (fusible_blocks) are skipped, which leaves the volume
bit-identical to warping all of them (tests check it).
The mesh extracted after fusion serves three uses: this frame's output (warped by W_t), the
nodes' coverage test, and the next frame's data term (DynamicFusion Sec. 3.3.1 extracts it
before the solve; it is the same mesh, so it is extracted once).
The regulariser can use DynamicFusion's hierarchical deformation tree (tracking.hierarchy,
hierarchy.py), as the shared tracker can for SurfelWarp.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from pykdtree.kdtree import KDTree

from .camera import Intrinsics
from .dual_quaternion import apply_components
from .gl.mesh_maps import render_mesh_maps
from .observation import CameraObservation
from .outputs import FrameRecord
from .pipeline import maps_to_world, transform_surfels
from .ply import vertex_table
from .se3 import invert
from .timing import StageTimer
from .tracking import SurfelSet, Tracker, TrackingParams
from .tsdf import TSDFParams, TSDFVolume, extract_mesh, fuse, node_distance_weight
from .warp_field import WarpField, WarpFieldParams, extend, inverse_warp, skin, update_skinning, warp


@dataclass(frozen=True)
class DynamicFusionParams:
    tsdf: TSDFParams = field(default_factory=TSDFParams)
    # node_radius_m is DynamicFusion's decimation density epsilon (25 mm, Sec. 4).
    warp_field: WarpFieldParams = field(default_factory=WarpFieldParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)   # the same tracker as SurfelWarp
    min_first_points: int = 500       # the model starts at the first frame with this many valid pixels
    voxel_chunk: int = 1 << 18        # voxels per warp / skinning batch (bounds temporaries)
    # Warp and fuse only blocks of voxels that can be fused this frame (fusible_blocks): the
    # same result as warping every voxel, at a fraction of the cost.
    cull_voxels: bool = True
    cull_block: int = 6               # block edge, voxels (4-8 all cost about the same)
    cull_margin_m: float = 0.004      # slack for the blend leaving the hull of its nodes' motions

    def to_dict(self) -> dict:
        return asdict(self)


def warp_points_fast(points: np.ndarray, knn: np.ndarray, weights: np.ndarray, field: WarpField,
                     chunk: int = 1 << 14) -> np.ndarray:
    """warp_field.warp for many points in float32: the same dual quaternion blend (each node's
    quaternion flipped into the hemisphere of the point's heaviest, i.e. first, node), done in
    cache-sized chunks without building per-point matrices. Several times faster than warp() on
    the voxel grid; agrees with it to float32 rounding (~1 um at 1 m)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    dq = field.dual_quaternions()
    table = dq.astype(np.float32)
    # Rotations of less than 90 degrees are less than 180 apart: no pair needs flipping then.
    calm = bool(np.all(dq[:, 0] > 0.7072 * np.linalg.norm(dq[:, :4], axis=1)))
    out = np.empty_like(points)
    for s in range(0, len(points), chunk):
        k, w = knn[s:s + chunk], weights[s:s + chunk]
        q = table[k]                                                      # (n, k, 8)
        if not calm:
            w = np.where(np.einsum("nki,ni->nk", q[..., :4], q[:, 0, :4]) < 0, -w, w)
        moved, _ = apply_components(np.einsum("vk,vkc->cv", w, q), points[s:s + chunk].T)
        out[s:s + chunk] = np.stack(moved, axis=-1)
    return out


# ---------------------------------------------------------------- voxels that can be fused

@dataclass(frozen=True)
class VoxelBlocks:
    """The voxel grid cut into cubes of `size`^3 voxels, each with the warp nodes that skin any
    of its voxels (rows padded by repeating their first node)."""
    size: int
    shape: tuple[int, int, int]   # blocks per axis
    first: np.ndarray             # (B, 3) float64 world centre of each block's first voxel
    last: np.ndarray              # (B, 3) float64 ... and of its last one
    nodes: np.ndarray             # (B, n) int32


def voxel_blocks(volume: TSDFVolume, knn: np.ndarray, num_nodes: int, size: int) -> VoxelBlocks:
    dims = np.array(volume.dims)
    shape = -(-dims // size)
    ids = [np.arange(d) // size for d in dims]
    block = ((ids[0][:, None, None] * shape[1] + ids[1][None, :, None]) * shape[2] + ids[2][None, None, :]).ravel()
    member = np.zeros((int(np.prod(shape)), num_nodes), bool)
    for slot in range(knn.shape[1]):
        member[block, knn[:, slot]] = True
    rows, cols = np.nonzero(member)
    count = np.bincount(rows, minlength=len(member))
    slot = np.arange(len(rows)) - np.repeat(np.cumsum(count) - count, count)
    nodes = np.zeros((len(member), max(int(count.max()), 1)), np.int32)
    nodes[rows, slot] = cols
    nodes = np.where(np.arange(nodes.shape[1]) < count[:, None], nodes, nodes[:, :1])
    ijk = np.stack(np.unravel_index(np.arange(len(member)), tuple(shape)), -1)
    first = volume.origin + ijk * size * volume.voxel_size
    last = volume.origin + np.minimum(ijk * size + size - 1, dims - 1) * volume.voxel_size
    return VoxelBlocks(size, tuple(int(x) for x in shape), first, last, nodes)


def _max_pyramid(image: np.ndarray) -> list[np.ndarray]:
    """Level l holds the maximum over 2^l x 2^l tiles (zero-padded at odd edges)."""
    levels = [image]
    while max(levels[-1].shape) > 1:
        a = levels[-1]
        h, w = a.shape
        a = np.pad(a, ((0, h % 2), (0, w % 2)))
        levels.append(a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2).max(axis=(1, 3)))
    return levels


def fusible_blocks(blocks: VoxelBlocks, field: WarpField, T_world_to_camera: np.ndarray, depth_m: np.ndarray,
                   intrinsics: Intrinsics, truncation_m: float, margin_m: float) -> np.ndarray:
    """(B,) bool, False for blocks none of whose voxels Eq. 4 can fuse this frame.

    A voxel x of a block goes to W(x) x, a dual quaternion blend of the motions G_j of its
    nodes. Every G_j x lies in the box spanned by G_j applied to the block's corners, and the
    blend stays within margin_m of the hull of the G_j x (it would be exactly inside if the
    nodes' rotations agreed; tests check the margin on strongly bent fields). A block is
    fusible only if that box, in the camera, projects onto a pixel whose depth + tau exceeds
    its nearest depth (psdf > -tau): a max-depth pyramid answers that for a rectangle with
    four lookups. Boxes reaching behind the camera plane are kept.
    """
    G = field.global_transforms()
    A = np.asarray(T_world_to_camera, np.float64) @ G
    # The box of a block under each node's motion: centre R c + t, half-extents |R| h.
    c = 0.5 * (blocks.first + blocks.last)
    h = 0.5 * (blocks.last - blocks.first)
    R, t = A[:, :3, :3], A[:, :3, 3]
    # The blend leaves that hull only as far as its nodes' rotations disagree, times the lever
    # arm: slack = margin + 0.5 * (largest angle to the block's first node) * (farthest node).
    # On random fields whose neighbouring nodes disagree by up to 0.4 rad the excursion needed
    # at most 0.06 * angle * arm (tests/test_dynamicfusion.py checks such a field).
    q = field.dual_quaternions()[:, :4]
    cos_half = np.abs(np.einsum("bni,bi->bn", q[blocks.nodes], q[blocks.nodes[:, 0]]))
    spread = 2 * np.arccos(np.clip(cos_half, 0, 1)).max(1)
    reach = np.linalg.norm(field.nodes[blocks.nodes] - c[:, None], axis=-1).max(1) + np.linalg.norm(h, axis=1)
    slack = margin_m + 0.5 * spread * reach
    lo = np.empty((len(c), 3))
    hi = np.empty((len(c), 3))
    for r in range(3):
        Rr = R[:, r, :][blocks.nodes]                                 # (B, n, 3)
        centre = np.einsum("bnj,bj->bn", Rr, c) + t[blocks.nodes, r]
        half = np.einsum("bnj,bj->bn", np.abs(Rr), h)
        lo[:, r] = (centre - half).min(1) - slack
        hi[:, r] = (centre + half).max(1) + slack
    near = 1e-3
    front = lo[:, 2] > near
    zs = np.where(front[:, None], np.stack([lo[:, 2], hi[:, 2]], -1), 1.0)        # (B, 2)
    u = intrinsics.fx * np.stack([lo[:, :1] / zs, hi[:, :1] / zs], -1).reshape(-1, 4) + intrinsics.cx
    v = intrinsics.fy * np.stack([lo[:, 1:2] / zs, hi[:, 1:2] / zs], -1).reshape(-1, 4) + intrinsics.cy
    h, w = depth_m.shape
    u0, u1 = np.floor(u.min(1)), np.ceil(u.max(1))
    v0, v1 = np.floor(v.min(1)), np.ceil(v.max(1))
    inside = front & (u1 >= 0) & (u0 <= w - 1) & (v1 >= 0) & (v0 <= h - 1)
    u0, u1 = (np.clip(a, 0, w - 1).astype(np.int64) for a in (u0, u1))
    v0, v1 = (np.clip(a, 0, h - 1).astype(np.int64) for a in (v0, v1))
    levels = _max_pyramid(np.asarray(depth_m, np.float32))
    extent = np.maximum(u1 - u0, v1 - v0) + 1
    level = np.minimum(np.ceil(np.log2(extent)).astype(np.int64), len(levels) - 1)
    deepest = np.zeros(len(lo), np.float32)
    for l in np.unique(level[inside]):
        sel = np.flatnonzero(inside & (level == l))
        a = levels[l]
        tu0, tu1, tv0, tv1 = u0[sel] >> l, u1[sel] >> l, v0[sel] >> l, v1[sel] >> l
        deepest[sel] = np.maximum(np.maximum(a[tv0, tu0], a[tv0, tu1]), np.maximum(a[tv1, tu0], a[tv1, tu1]))
    # Invalid pixels hold 0, below any positive depth; a box starting within tau of the
    # camera plane passes even there (conservative).
    return (hi[:, 2] > near) & (~front | (inside & (deepest > lo[:, 2] - truncation_m)))


def block_voxels(blocks: VoxelBlocks, keep: np.ndarray, dims: tuple[int, int, int]) -> np.ndarray:
    """Flat indices (ascending) of the voxels of the kept blocks."""
    grid = keep.reshape(blocks.shape)
    for axis in range(3):
        grid = np.repeat(grid, blocks.size, axis=axis)
    return np.flatnonzero(grid[:dims[0], :dims[1], :dims[2]])


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
        self.voxel_knn = self.voxel_weights = self.voxel_fusion_weight = None
        self.voxel_centres: np.ndarray | None = None   # (V, 3) float32, cached: the grid never moves
        self.blocks: VoxelBlocks | None = None
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
        T_rendered = self.T_camera_to_world.copy()
        maps = render_mesh_maps(*transform_surfels(invert(T_rendered), mesh.live_vertices, mesh.live_normals),
                                mesh.faces, self.intrinsics)
        timer.lap("solver_maps")

        rigid = self.tracker.rigid(*maps_to_world(maps, T_rendered), obs,
                                   self.tracker.stillness_map(maps.index, mesh.knn, mesh.weights))
        timer.lap("rigid")

        surfels = self.predicted_points(maps, T_rendered)
        timer.lap("predict")
        solved, nonrigid = self.tracker.nonrigid(self.field, surfels, obs)
        self.field = self.tracker.factor(solved, nonrigid)
        timer.lap("nonrigid")

        depth = self._depth(obs)
        ids = self.fusible_voxels(depth)
        warped = self.warp_voxels(ids)
        timer.lap("warp")
        weight = self.voxel_fusion_weight if ids is None else self.voxel_fusion_weight[ids]
        fused = fuse(self.volume, warped, weight, invert(self.T_camera_to_world), depth, self.intrinsics, p.tsdf,
                     voxels=ids)
        del warped, weight
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
                                   "warped_voxels": self.volume.num_voxels if ids is None else len(ids),
                                   "data_points": len(surfels.positions), "correspondences": nonrigid.correspondences,
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
                self.voxel_centres = volume.voxel_centres()
                self.field = WarpField.from_points(vertices, p.warp_field)
                self.voxel_knn, self.voxel_weights = self._skin_voxels()
                self._update_fusion_weights()
                self._update_blocks()
                self._set_mesh(vertices, normals, faces)
                self.reference_frame = obs.frame_index
                self.T_reference_camera_to_world = self.T_camera_to_world.copy()
        timer.lap("initialise")
        return self._record(obs, timer, extra={})

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
        Blocks whose every voxel is nearer to all of its nodes than to any new node are skipped
        without looking at their voxels.
        """
        field, k = self.field, self.params.warp_field.k_skin
        if first_new < k:   # padded slots: the k-th slot is not the k-th nearest node
            ids = np.arange(self.volume.num_voxels)
        else:
            b = self.blocks
            c = 0.5 * (b.first + b.last)
            half = np.linalg.norm(0.5 * (b.last - b.first), axis=1)
            reach = np.linalg.norm(field.nodes[b.nodes] - c[:, None], axis=-1).max(1) + half
            d_new, _ = KDTree(field.nodes[first_new:]).query(c.astype(np.float32), k=1)
            ids = block_voxels(b, d_new.reshape(-1) - half <= reach, self.volume.dims)
            if len(ids):
                centres = self.voxel_centres[ids]
                kth = field.nodes[self.voxel_knn[ids, -1]] - centres
                d, _ = KDTree(field.nodes[first_new:]).query(centres, k=1)
                ids = ids[d.reshape(-1) ** 2 < np.einsum("ij,ij->i", kth, kth)]
        for s in range(0, len(ids), self.params.voxel_chunk):
            g = ids[s:s + self.params.voxel_chunk]
            centres = self.voxel_centres[g]
            self.voxel_knn[g], self.voxel_weights[g] = update_skinning(
                self.voxel_knn[g], self.voxel_weights[g], centres, field, first_new)
            self.voxel_fusion_weight[g] = node_distance_weight(
                centres, field.nodes, self.voxel_knn[g], self.params.warp_field.node_radius_m)
        self._update_blocks()

    def _update_fusion_weights(self) -> None:
        """w(x) of Sec. 3.2, from the canonical nodes only: it changes only when nodes are added."""
        w = np.empty(self.volume.num_voxels, np.float32)
        for start, stop, centres in self._chunks():
            w[start:stop] = node_distance_weight(centres, self.field.nodes, self.voxel_knn[start:stop],
                                                 self.params.warp_field.node_radius_m)
        self.voxel_fusion_weight = w

    def fusible_voxels(self, depth_m: np.ndarray) -> np.ndarray | None:
        """Flat indices of the voxels that Eq. 4 may fuse this frame (None: all of them, when
        culling is off). Whole blocks are dropped only when no voxel in them can land in front
        of the depth + tau, so fusion gives the same volume as warping every voxel."""
        p = self.params
        if not p.cull_voxels:
            return None
        keep = fusible_blocks(self.blocks, self.field, invert(self.T_camera_to_world), depth_m, self.intrinsics,
                              p.tsdf.truncation_m, p.cull_margin_m)
        return block_voxels(self.blocks, keep, self.volume.dims)

    def warp_voxels(self, ids: np.ndarray | None = None) -> np.ndarray:
        """Voxel centres (flat indices `ids`, default all) moved by the warp field W, world,
        (n, 3) float32: the same dual quaternion blend as the surface (Sec. 3.2)."""
        if ids is None:
            return warp_points_fast(self.voxel_centres, self.voxel_knn, self.voxel_weights, self.field)
        return warp_points_fast(self.voxel_centres[ids], self.voxel_knn[ids], self.voxel_weights[ids], self.field)

    def _update_blocks(self) -> None:
        self.blocks = voxel_blocks(self.volume, self.voxel_knn, self.field.num_nodes, self.params.cull_block)

    def _set_mesh(self, vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> None:
        wf = self.field.params
        knn, weights = skin(vertices, self.field.nodes, wf.k_skin, self.field.sigma_m)
        live, live_n = warp(vertices, normals, knn, weights, self.field)
        self.mesh = CanonicalMesh(vertices, normals, faces, knn, weights, live, live_n)

    def model_bytes(self) -> dict[str, int]:
        """Memory held by the model: the volume, the voxel node field (k-NN, skinning and fusion
        weights, centres, block node sets), the canonical mesh and the warp field."""
        if self.volume is None:
            return {"volume": 0, "voxel_field": 0, "mesh": 0, "warp_field": 0}
        f = self.field
        return {"volume": self.volume.nbytes,
                "voxel_field": self.voxel_knn.nbytes + self.voxel_weights.nbytes + self.voxel_fusion_weight.nbytes
                + self.voxel_centres.nbytes + self.blocks.nodes.nbytes,
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
