"""Compiled (numba) loops of fusion's two index-map searches: each depth pixel's best surfel in
its window, and near-duplicate surfels on neighbouring fine pixels. In numpy both were a pass
per window slot or neighbour offset over every candidate (tube-wall, 275k surfels: 53 and 35 ms
a frame); here one pass over the pixels or surfels (a few ms). fusion.py holds the semantics.

The three searches run their pixels or surfels on numba's threads: each pixel's answer is its
own, and the duplicate marking only ever sets flags, so no answer depends on the order or the
thread count (a test runs them on one thread and on two). The model update runs on one core
otherwise; on 7-Scenes they took the fuse, append and remove stages 158 / 157 -> 133 / 130 ms."""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def _gap(points, normals, k, vertex, normal, p):
    """Squared distance between surfel k and depth pixel p, and their normals' dot product, each
    summed left to right (as numpy's einsum does over three components)."""
    d0 = points[k, 0] - vertex[p, 0]
    d1 = points[k, 1] - vertex[p, 1]
    d2 = points[k, 2] - vertex[p, 2]
    return d0 * d0 + d1 * d1 + d2 * d2, normals[k, 0] * normal[p, 0] + normals[k, 1] * normal[p, 1] + \
        normals[k, 2] * normal[p, 2]


@numba.njit(cache=True, nogil=True, parallel=True)
def best_in_windows(index, origin_rows, origin_cols, window, points, normals, vertex, normal, gate2,
                    normal_threshold, confidence, best_k, best_d2):
    """For pixel p (its depth vertex and normal, gate2 its squared distance gate): among the
    surfels on the window x window fine pixels from (origin_rows[p], origin_cols[p]) that pass
    both gates, the highest confidence, then the smallest distance, then the first in row-major
    window order, into best_k[p] (-1: none) and best_d2[p]."""
    h, w = index.shape
    for p in numba.prange(len(origin_rows)):
        best, best_conf, best_dist = -1, np.float32(-np.inf), np.float32(np.inf)
        for dy in range(window):
            y = origin_rows[p] + dy
            if y < 0 or y >= h:
                continue
            for dx in range(window):
                x = origin_cols[p] + dx
                if x < 0 or x >= w:
                    continue
                k = index[y, x]
                if k < 0:
                    continue
                dist, dot = _gap(points, normals, k, vertex, normal, p)
                if not (dist <= gate2[p] and dot >= normal_threshold):
                    continue
                c = confidence[k]
                if c > best_conf or (c == best_conf and dist < best_dist):
                    best, best_conf, best_dist = k, c, dist
        best_k[p] = best
        best_d2[p] = best_dist


@numba.njit(cache=True, nogil=True, parallel=True)
def mark_redundant(index, surfels, fine_rows, fine_cols, reach, position, normal, radius, confidence,
                   distance_ratio, normal_threshold, drop):
    """For each surfel j on fine pixel (fine_rows, fine_cols) and each surfel i on the pixels
    within `reach` of it (i != j): if they are closer than distance_ratio * min(r_i, r_j) with
    dot(n_i, n_j) > normal_threshold, mark the one of lower confidence (ties: higher index)."""
    h, w = index.shape
    for q in numba.prange(len(surfels)):
        j = surfels[q]
        for dy in range(-reach, reach + 1):
            y = fine_rows[q] + dy
            if y < 0 or y >= h:
                continue
            for dx in range(-reach, reach + 1):
                x = fine_cols[q] + dx
                if x < 0 or x >= w:
                    continue
                i = index[y, x]
                if i < 0 or i == j:
                    continue
                d0 = position[j, 0] - position[i, 0]
                d1 = position[j, 1] - position[i, 1]
                d2 = position[j, 2] - position[i, 2]
                limit = distance_ratio * min(radius[j], radius[i])
                dot = normal[j, 0] * normal[i, 0] + normal[j, 1] * normal[i, 1] + normal[j, 2] * normal[i, 2]
                if d0 * d0 + d1 * d1 + d2 * d2 < limit * limit and dot > normal_threshold:
                    cj, ci = confidence[j], confidence[i]
                    if cj < ci or (cj == ci and j > i):
                        drop[j] = True
                    else:
                        drop[i] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def mark_covered(index, s, rows, cols, reach, points, normals, depth_v, depth_n, max_d2, covered):
    """covered[p] for depth pixel (rows[p], cols[p]): a surfel on the fine pixels of a depth
    pixel within `reach` of it (index at supersampling s) lies within max_d2 (squared) of its
    vertex on the same side (normals' dot > 0). The numpy passes it replaced, one an offset,
    made unmatched_depth_pixels 3.7 ms a hand's frame (2.1 now); _gap's float32 sums are in
    numpy einsum's order, so the same pixels are covered."""
    h, w = index.shape[0] // s, index.shape[1] // s
    side = 2 * reach + 1
    for p in numba.prange(len(rows)):
        for o in range(side * side):            # offsets row by row
            y, x = rows[p] + o // side - reach, cols[p] + o % side - reach
            if covered[p]:
                break
            if y < 0 or y >= h or x < 0 or x >= w:
                continue
            for fy in range(s * y, s * y + s):
                for fx in range(s * x, s * x + s):
                    k = index[fy, fx]
                    if k < 0:
                        continue
                    dist, dot = _gap(points, normals, k, depth_v, depth_n, p)
                    if dist <= max_d2[p] and dot > 0:
                        covered[p] = True


@numba.njit(cache=True, nogil=True, parallel=True)
def fuse_rows(k, pix, depth_v, depth_n, depth_conf, depth_radius, depth_color, time, position, normal, radius,
              confidence, t_observed, color, color_weight):
    """Eq. 5 for pair p (surfel k[p], depth pixel pix[p]; its vertex and normal depth_v[p],
    depth_n[p] in world) into the model's arrays (copies), in float32 and in the order of
    fusion.fuse_reference's numpy expressions, so that the results agree to the bit. Colour
    (depth_color (H*W, 3), empty without it) fuses with its own weight. The surfels k are
    distinct (fusion.fuse), so the pairs run on numba's threads, each writing its own surfel."""
    tiny, floor = np.float32(1e-30), np.float32(1e-12)
    for p in numba.prange(len(k)):
        i, c_depth = k[p], depth_conf[pix[p]]
        c_old = confidence[i]
        c_new = c_old + c_depth
        a = c_old / max(c_new, tiny)
        b = c_depth / max(c_new, tiny)
        n0 = a * normal[i, 0] + b * depth_n[p, 0]
        n1 = a * normal[i, 1] + b * depth_n[p, 1]
        n2 = a * normal[i, 2] + b * depth_n[p, 2]
        norm = max(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), floor)
        normal[i, 0], normal[i, 1], normal[i, 2] = n0 / norm, n1 / norm, n2 / norm
        for j in range(3):
            position[i, j] = a * position[i, j] + b * depth_v[p, j]
        radius[i] = a * radius[i] + b * depth_radius[pix[p]]
        confidence[i] = c_new
        t_observed[i] = time
        if len(depth_color):
            w_new = color_weight[i] + c_depth
            step = c_depth / max(w_new, tiny)
            for j in range(3):
                old = color[i, j]
                color[i, j] = old + step * (np.float32(depth_color[pix[p], j]) - old)
            color_weight[i] = w_new
