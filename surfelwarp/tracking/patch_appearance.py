"""The appearance side of patch_align: a patch's shading taken out of it and of the steepest
descent images (Baker & Matthews, "Lucas-Kanade 20 years on", part 3, projecting out an
appearance basis). The basis is gain (the template itself), offset, and a plane of offset in x
and y: a lamp beside the camera shades a curved surface unevenly across a 13 px patch, and the
model's colour was fused under the lamp's earlier directions.
"""
from __future__ import annotations

import numba
import numpy as np

# The sums over a patch may be reordered (and so vectorised): the kernel takes ~30 % less time on
# a twist-limb frame's 4.2k flow pairs, the results move by 1e-13 px. Not numba's fastmath=True:
# that assumes no infinities, and a step is inf where an alignment runs away.
SUMS = {"reassoc", "contract"}


@numba.njit(cache=True)
def plane_basis(w, ox, oy):
    """(3, S): 1, x and y over the patch made orthonormal under the weights w (Gram-Schmidt),
    so that removing a patch's weighted plane is three sums and three subtractions."""
    S = len(w)
    E = np.empty((3, S))
    E[0, :], E[1, :], E[2, :] = 1.0, ox, oy
    for k in range(3):
        for j in range(k):
            acc = 0.0
            for s in range(S):
                acc += w[s] * E[k, s] * E[j, s]
            for s in range(S):
                E[k, s] -= acc * E[j, s]
        norm = 0.0
        for s in range(S):
            norm += w[s] * E[k, s] * E[k, s]
        norm = np.sqrt(norm)
        for s in range(S):
            E[k, s] = E[k, s] / norm if norm > 1e-9 else 0.0
    return E


@numba.njit(cache=True, fastmath=SUMS)
def remove_plane(v, w, E, out):
    """out = v less its weighted least-squares plane (E from plane_basis)."""
    S = len(v)
    for s in range(S):
        out[s] = v[s]
    for k in range(3):
        acc = 0.0
        for s in range(S):
            acc += w[s] * out[s] * E[k, s]
        for s in range(S):
            out[s] -= acc * E[k, s]


@numba.njit(cache=True, fastmath=SUMS)
def normalise(v, w, E, out):
    """out = (v - its plane) / std, both weighted by w; returns std."""
    remove_plane(v, w, E, out)
    sw = var = 0.0
    for s in range(len(v)):
        sw += w[s]
        var += w[s] * out[s] * out[s]
    sd = max(np.sqrt(var / max(sw, 1e-12)), 1e-6)
    for s in range(len(v)):
        out[s] /= sd
    return sd


@numba.njit(cache=True, fastmath=SUMS)
def centred(v, w, E, out):
    """out = (v - mean) / std of v less its plane, in one pass of sums (E orthonormal: the plane
    takes its coefficients' squares off the sum of squares). The plane itself is left in: the
    steepest descent images are projected off it, so it moves no step (nor where the steps end),
    and the iterations save two passes."""
    S = len(v)
    sw = c0 = c1 = c2 = sq = 0.0
    for s in range(S):
        wv = w[s] * v[s]
        sw += w[s]
        c0 += wv * E[0, s]
        c1 += wv * E[1, s]
        c2 += wv * E[2, s]
        sq += wv * v[s]
    mean = c0 * E[0, 0] if sw > 0 else 0.0
    sd = max(np.sqrt(max(sq - c0 * c0 - c1 * c1 - c2 * c2, 0.0) / max(sw, 1e-12)), 1e-6)
    for s in range(S):
        out[s] = (v[s] - mean) / sd
    return sd


@numba.njit(cache=True, fastmath=SUMS)
def project_out(SD, w, E, Tn):
    """Project the steepest descent images (the rows of SD, in place) off the span of the patch's
    plane and Tn (the shading's gain, offset and slope across the patch); their Gauss-Newton
    matrix. Each sum runs along a row into a local variable, which the compiler can vectorise
    (not into an element of H)."""
    S = len(w)
    tn2 = 0.0
    for s in range(S):
        tn2 += w[s] * Tn[s] * Tn[s]
    row = np.empty(S)
    for k in range(6):
        sd = SD[k]
        remove_plane(sd, w, E, row)
        along = 0.0
        for s in range(S):
            along += w[s] * row[s] * Tn[s]
        along /= max(tn2, 1e-12)
        for s in range(S):
            sd[s] = row[s] - along * Tn[s]
    H = np.empty((6, 6))
    for i in range(6):
        for j in range(i, 6):
            acc = 0.0
            for s in range(S):
                acc += w[s] * SD[i, s] * SD[j, s]
            H[i, j] = acc
            H[j, i] = acc
    for i in range(6):
        H[i, i] += 1e-6
    return H
