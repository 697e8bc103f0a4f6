"""Blocks of voxels and which of them can be fused this frame.

Every voxel fusion touches is warped by the full dual quaternion blend; blocks of voxels that
provably cannot be fused this frame (fusible_blocks) are skipped, which leaves the volume
bit-identical to warping all of them (tests check it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelwarp.deform.warp_field import WarpField
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.dq_kernels import blend_apply
from surfelwarp.methods.dynamicfusion.tsdf import TSDFVolume

def warp_points_fast(points: np.ndarray, knn: np.ndarray, weights: np.ndarray, field: WarpField,
                     chunk: int = 1 << 16) -> np.ndarray:
    """warp_field.warp for many points (the voxel grid), float32 out: the compiled blend warp
    (the one the surfels use, dq_kernels.blend_apply) in chunks that bound its float64 copies."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    dq = field.dual_quaternions()
    out = np.empty_like(points)
    for s in range(0, len(points), chunk):
        _, _, moved, _ = blend_apply(dq, knn[s:s + chunk], weights[s:s + chunk], points[s:s + chunk].T)
        out[s:s + chunk] = moved.T
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
    # at most 0.06 * angle * arm (tests/methods/dynamicfusion/test_dynamicfusion.py checks such a field).
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
