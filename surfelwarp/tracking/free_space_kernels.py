"""The free-space term's compiled loops (free_space.py): the projection of the points within
reach, the search about each point, and the nearest depth within the occluder test's ball from
its rows' minima (nearest_depth, from the image, is the reference the tests hold them to)."""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def chamfer(dy, dx):
    """cv2's DIST_MASK_5 chamfer distance of a pixel offset (steps 1, diagonals 1.4, knight's
    moves 2.1969) with nothing in the way: what its two-pass transform gives, to 5e-5 px."""
    big, small = max(abs(dy), abs(dx)), min(abs(dy), abs(dx))
    if big >= 2 * small:
        return small * 2.1969 + (big - 2 * small)
    return (big - small) * 2.1969 + (2 * small - big) * 1.4


@numba.njit(cache=True, nogil=True)
def nearest_depth(depth, ball, y, x):
    """The nearest depth measured within the ball about pixel (y, x) (inf if none): the reference
    for nearest_by_rows."""
    h, w = depth.shape
    r = len(ball) // 2
    m = np.inf
    for dy in range(-r, r + 1):
        yy = y + dy
        if 0 <= yy < h:
            for xx in range(max(x - ball[dy + r], 0), min(x + ball[dy + r], w - 1) + 1):
                d = depth[yy, xx]
                if d > 0 and d < m:
                    m = d
    return m


@numba.njit(cache=True, nogil=True)
def row_minima(depth, slot, r0, r1, c0, c1):
    """(slots, r1 - r0, c1 - c0) float32: for each half-width b with slot[b] >= 0, the least depth
    measured (> 0) along each row within b columns of each pixel (inf if none). Columns beyond
    c0:c1, in the image or not, count as unmeasured, so the box must reach len(slot) - 1 columns
    past every measured pixel of rows r0:r1 (or the image's edge). Width b is width b - 1's
    minima at the columns either side, for b of 2 or more: two comparisons a pixel each."""
    C = c1 - c0
    out = np.full((slot.max() + 1, r1 - r0, C), np.inf, np.float32)
    prev, cur = np.empty(C, np.float32), np.empty(C, np.float32)
    for y in range(r0, r1):
        for x in range(C):
            d = depth[y, c0 + x]
            prev[x] = d if d > 0 else np.inf
        if slot[0] >= 0:
            out[slot[0], y - r0] = prev
        for b in range(1, len(slot)):
            for x in range(C):
                left = prev[x - 1] if x > 0 else np.inf
                right = prev[x + 1] if x < C - 1 else np.inf
                cur[x] = min(left, right) if b > 1 else min(left, prev[x], right)
            prev, cur = cur, prev
            if slot[b] >= 0:
                out[slot[b], y - r0] = prev
    return out


@numba.njit(cache=True, nogil=True)
def nearest_by_rows(minima, slot, box, ball, y, x):
    """nearest_depth from the rows' minima that row_minima made over box (r0, r1, c0, c1),
    whose rows hold every measured pixel and whose columns reach the ball's half-width past
    them: the same value, from 2 r + 1 reads."""
    r0, r1, c0, c1 = box[0], box[1], box[2], box[3]
    if x < c0 or x >= c1:
        return np.inf
    r = len(ball) // 2
    m = np.inf
    for dy in range(-r, r + 1):
        yy = y + dy
        if r0 <= yy < r1:
            v = minima[slot[ball[dy + r]], yy - r0, x - c0]
            if v < m:
                m = v
    return m


@numba.njit(cache=True, nogil=True)
def within_reach(x, R, t, fx, fy, cx, cy, h, w, reach, margin, sel, uv, q):
    """The world points (3, N) in front of the camera, projecting inside the image (a pixel
    from its last row and column) and nearer than their pixel's reach by more than `margin`:
    their indices, sub-pixel (u, v) and camera points, written from the start of sel, uv and
    q; their count. numpy's arithmetic, in its order."""
    k = 0
    for j in range(x.shape[1]):
        q2 = x[0, j] * R[2, 0] + x[1, j] * R[2, 1] + x[2, j] * R[2, 2] + t[2]
        if not q2 > 1e-3:
            continue
        q0 = x[0, j] * R[0, 0] + x[1, j] * R[0, 1] + x[2, j] * R[0, 2] + t[0]
        q1 = x[0, j] * R[1, 0] + x[1, j] * R[1, 1] + x[2, j] * R[1, 2] + t[1]
        inv = 1.0 / q2
        u = fx * q0 * inv + cx
        v = fy * q1 * inv + cy
        if not (u >= 0 and u < w - 1 and v >= 0 and v < h - 1):
            continue
        if not q2 + margin < reach[int(v) * w + int(u)]:
            continue
        sel[k] = j
        uv[0, k], uv[1, k] = u, v
        q[0, k], q[1, k], q[2, k] = q0, q1, q2
        k += 1
    return k


@numba.njit(cache=True, nogil=True)
def search(depth, empty, nearer, ball, minima, slot, box, rows, cols, layers, layer_m, margin_m, max_px,
           found_layer, found, out):
    """out[i, j]: the chamfer distance from pixel j of point i ((rows, cols) + (0, 0), (0, 1),
    (1, 0), (1, 1)) to the nearest pixel consistent with layer layers[i] (FreeSpace._transform),
    found ring by ring; -1 if none is within max_px. A pixel at Chebyshev distance r is at
    chamfer distance r or more, so the search ends at the first ring beyond the best. The
    nearest depths it needs are memoised in `nearer`, from the rows' `minima`; each pixel's last
    answer in `found`, with its layer in `found_layer` (-1: none yet): a solve asks again for
    nearly the same pixels and layers."""
    h, w = depth.shape
    for i in range(len(rows)):
        k = layers[i]
        near = np.float32(k * layer_m - margin_m)      # nearer than this: an occluder
        behind = np.float32((k + 1) * layer_m + margin_m)   # farther than this: seen through
        for j in range(4):
            y, x = rows[i] + j // 2, cols[i] + j % 2
            if found_layer[y, x] == k:
                out[i, j] = found[y, x]
                continue
            best = np.inf
            for r in range(max_px + 1):
                if r > best:
                    break
                for dy in range(-r, r + 1):
                    yy = y + dy
                    if yy < 0 or yy >= h:
                        continue
                    step = 1 if dy == -r or dy == r else 2 * r
                    for dx in range(-r, r + 1, step):
                        xx = x + dx
                        if xx < 0 or xx >= w:
                            continue
                        c = chamfer(dy, dx)
                        if c >= best:
                            continue
                        if empty[yy, xx]:
                            m = nearer[yy, xx]
                            if np.isnan(m):
                                m = nearer[yy, xx] = nearest_by_rows(minima, slot, box, ball, yy, xx)
                            consistent = m < near
                        else:
                            consistent = not depth[yy, xx] > behind
                        if consistent:
                            best = c
            out[i, j] = best if best <= max_px + 1 else -1.0
            found_layer[y, x], found[y, x] = k, out[i, j]
