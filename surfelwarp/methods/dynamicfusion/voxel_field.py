"""The canonical volume's voxels with the warp field's nodes (DynamicFusion Sec. 3.2-3.4).

Each voxel keeps its k nearest nodes and skinning weights (the discretised k-nearest-node
field of Sec. 3.3.3), its fusion weight w(x) (Sec. 3.2, from its distance to the nodes), and
the volume is cut into blocks with the nodes that skin them (voxel_blocks.py), so fusion can
skip the blocks that cannot be fused. `VoxelField` keeps all of them in step as nodes are added
(`nodes_added`) and as the volume grows over surface seen outside it (`grow`).
"""
from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from surfelwarp.deform.warp_field import WarpField, skin, update_skinning
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.methods.dynamicfusion.params import DynamicFusionParams
from surfelwarp.methods.dynamicfusion.tsdf import TSDFVolume, node_distance_weight
from surfelwarp.methods.dynamicfusion.voxel_blocks import block_voxels, fusible_blocks, voxel_blocks, warp_points_fast


class VoxelField:
    def __init__(self, volume: TSDFVolume, field: WarpField, params: DynamicFusionParams):
        self.volume, self.params = volume, params
        self.centres = volume.voxel_centres()      # (V, 3) float32, cached: voxels never move
        k = params.warp_field.k_skin
        self.knn = np.empty((volume.num_voxels, k), np.int32)
        self.weights = np.empty((volume.num_voxels, k), np.float32)
        self.fusion_weight = np.empty(volume.num_voxels, np.float32)
        self._skin(np.arange(volume.num_voxels), field)
        self.blocks = voxel_blocks(volume, self.knn, field.num_nodes, params.cull_block)

    @property
    def nbytes(self) -> int:
        return self.knn.nbytes + self.weights.nbytes + self.fusion_weight.nbytes + self.centres.nbytes + \
            self.blocks.nodes.nbytes

    def _skin(self, ids: np.ndarray, field: WarpField) -> None:
        """Skinning and fusion weights of voxels `ids` from scratch, in chunks."""
        k, step = self.params.warp_field.k_skin, self.params.voxel_chunk
        for s in range(0, len(ids), step):
            g = ids[s:s + step]
            centres = self.centres[g]
            self.knn[g], self.weights[g] = skin(centres, field.nodes, k, field.sigma_m)
            self.fusion_weight[g] = node_distance_weight(centres, field.nodes, self.knn[g],
                                                         self.params.warp_field.node_radius_m)

    def nodes_added(self, field: WarpField, first_new: int) -> None:
        """Skinning and fusion weights after nodes first_new.. were added (Sec. 3.4).

        A voxel's k nearest nodes change only if a new node is nearer than its current k-th
        one, so only those voxels go through update_skinning (near the new nodes: a few %).
        Blocks whose every voxel is nearer to all of its nodes than to any new node are skipped
        without looking at their voxels.
        """
        k = self.params.warp_field.k_skin
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
                centres = self.centres[ids]
                kth = field.nodes[self.knn[ids, -1]] - centres
                d, _ = KDTree(field.nodes[first_new:]).query(centres, k=1)
                ids = ids[d.reshape(-1) ** 2 < np.einsum("ij,ij->i", kth, kth)]
        for s in range(0, len(ids), self.params.voxel_chunk):
            g = ids[s:s + self.params.voxel_chunk]
            centres = self.centres[g]
            self.knn[g], self.weights[g] = update_skinning(self.knn[g], self.weights[g], centres, field, first_new)
            self.fusion_weight[g] = node_distance_weight(centres, field.nodes, self.knn[g],
                                                         self.params.warp_field.node_radius_m)
        self.blocks = voxel_blocks(self.volume, self.knn, field.num_nodes, self.params.cull_block)

    def grow(self, points_world: np.ndarray, field: WarpField) -> tuple[int, bool]:
        """Extend the volume on its grid over the points (depth at the tracked pose) that come
        within a truncation band of its border, plus margin_m: the voxel size and truncation
        stay, new voxels are unobserved and skinned to the nodes. DynamicFusion's volume is
        fixed; a camera that turns to new surface needs this. Returns the voxels added, and
        whether points were outside but growing would pass max_voxels (they are not fused then)."""
        p, volume = self.params.tsdf, self.volume
        points = np.asarray(points_world, np.float64).reshape(-1, 3)
        if len(points) == 0:
            return 0, False
        band = volume.truncation_m(p)
        lo, hi = points.min(0), points.max(0)
        if not any(a.any() for a in volume.padding(lo - band, hi + band)):
            return 0, False
        before, after = volume.padding(lo - p.margin_m, hi + p.margin_m)
        if np.prod(np.array(volume.dims) + before + after) > p.max_voxels:
            return 0, True
        grown, place = volume.padded(before, after)
        k, old = self.params.warp_field.k_skin, volume.dims
        knn = np.zeros(grown.dims + (k,), np.int32)
        weights = np.zeros(grown.dims + (k,), np.float32)
        fusion_weight = np.zeros(grown.dims, np.float32)
        knn[place], weights[place] = self.knn.reshape(old + (k,)), self.weights.reshape(old + (k,))
        fusion_weight[place] = self.fusion_weight.reshape(old)
        new = np.ones(grown.dims, bool)
        new[place] = False
        self.volume, self.centres = grown, grown.voxel_centres()
        self.knn, self.weights = knn.reshape(-1, k), weights.reshape(-1, k)
        self.fusion_weight = fusion_weight.reshape(-1)
        ids = np.flatnonzero(new)
        self._skin(ids, field)
        self.blocks = voxel_blocks(grown, self.knn, field.num_nodes, self.params.cull_block)
        return len(ids), False

    def fusible(self, field: WarpField, T_world_to_camera: np.ndarray, depth_m: np.ndarray,
                intrinsics: Intrinsics) -> np.ndarray:
        """Flat indices of the voxels that Eq. 4 may fuse this frame. Whole blocks are dropped
        only when no voxel in them can land in front of the depth + tau, so fusion gives the
        same volume as warping every voxel."""
        keep = fusible_blocks(self.blocks, field, T_world_to_camera, depth_m, intrinsics,
                              self.volume.truncation_m(self.params.tsdf), self.params.cull_margin_m)
        return block_voxels(self.blocks, keep, self.volume.dims)

    def warp(self, field: WarpField, ids: np.ndarray | None = None) -> np.ndarray:
        """Voxel centres (flat indices `ids`, default all) moved by the warp field W, world,
        (n, 3) float32: the same dual quaternion blend as the surface (Sec. 3.2)."""
        if ids is None:
            return warp_points_fast(self.centres, self.knn, self.weights, field)
        return warp_points_fast(self.centres[ids], self.knn[ids], self.weights[ids], field)
