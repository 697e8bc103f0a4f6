import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.index_map import render_index_map

K = Intrinsics(570.0, 565.0, 319.5, 239.5, 640, 480)


pytestmark = pytest.mark.usefixtures("gl")     # every test here renders


def random_surfels(n, seed=0):
    """Points with distinct random depths spread over (and a little beyond) the image."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.4, 3.0, n)
    u = rng.uniform(-10, K.width + 10, n)
    v = rng.uniform(-10, K.height + 10, n)
    p = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1).astype(np.float32)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return p, nrm.astype(np.float32), rng.uniform(0, 50, n).astype(np.float32)


def reference_index(p, intr):
    """Nearest pixel centre, closest surfel per pixel (z-buffer by lexsort)."""
    uv = intr.project(p.astype(np.float64))
    pix = np.floor(uv + 0.5).astype(np.int64)
    ok = (p[:, 2] > 0.01) & (pix[:, 0] >= 0) & (pix[:, 0] < intr.width) \
        & (pix[:, 1] >= 0) & (pix[:, 1] < intr.height)
    idx = np.flatnonzero(ok)
    lin = pix[idx, 1] * intr.width + pix[idx, 0]
    order = np.lexsort((p[idx, 2], lin))
    lin, idx = lin[order], idx[order]
    first = np.r_[True, lin[1:] != lin[:-1]]
    out = np.full(intr.width * intr.height, -1, np.int32)
    out[lin[first]] = idx[first]
    return out.reshape(intr.height, intr.width)


@pytest.mark.parametrize("groups_x", [None, 7])     # 7: the work groups on a 2-D grid, as past 4.2M surfels
@pytest.mark.parametrize("supersample", [1, 4])
def test_index_map_matches_numpy_projection(supersample, groups_x, monkeypatch):
    if groups_x:
        monkeypatch.setattr("surfelwarp.render.scatter.MAX_GROUPS_X", groups_x)
    p, n, c = random_surfels(60_000, seed=supersample)
    maps = render_index_map(p, n, K, supersample=supersample, confidence=c)
    intr = K.supersampled(supersample)
    assert maps.intrinsics == intr and maps.supersample == supersample
    assert maps.index.shape == (480 * supersample, 640 * supersample) and maps.index.dtype == np.int32
    assert maps.vertex.shape == maps.index.shape + (3,) and maps.vertex.dtype == np.float32
    ref = reference_index(p, intr)
    covered = (ref >= 0) | (maps.index >= 0)
    agree = (ref == maps.index)[covered].mean()
    assert agree >= 0.999, agree
    # At 1x many surfels share a pixel, so the depth test is exercised.
    if supersample == 1:
        assert (ref >= 0).sum() < 0.9 * len(p)
    hit = maps.index >= 0
    np.testing.assert_array_equal(maps.vertex[hit], p[maps.index[hit]])
    np.testing.assert_array_equal(maps.normal[hit], n[maps.index[hit]])
    np.testing.assert_array_equal(maps.confidence[hit], c[maps.index[hit]])
    assert not maps.vertex[~hit].any() and not maps.normal[~hit].any()


def test_rows_top_down_and_supersampled_pixel_centres():
    # Two points on the centre of depth pixels (u, v) = (10, 3) and (600, 470), nudged off the
    # exact 4x4 block centre (a rounding tie) towards the block's top-left sub-pixel of the
    # central 2x2.
    intr = K.supersampled(4)
    uv = np.array([[10.0, 3.0], [600.0, 470.0]]) - 0.1 / 4
    z = np.array([1.0, 2.0])
    p = np.stack([(uv[:, 0] - K.cx) / K.fx * z, (uv[:, 1] - K.cy) / K.fy * z, z], 1)
    maps = render_index_map(p, np.tile([0, 0, -1.0], (2, 1)), K, supersample=4)
    assert maps.index[3 * 4 + 1, 10 * 4 + 1] == 0
    assert maps.index[470 * 4 + 1, 600 * 4 + 1] == 1
    assert (maps.index >= 0).sum() == 2
    np.testing.assert_allclose(intr.project(p.astype(np.float64))[0], [41.4, 13.4], atol=1e-9)
    assert maps.confidence is None


def test_nearest_surfel_wins_whatever_the_draw_order():
    ray = np.array([(100 - K.cx) / K.fx, (50 - K.cy) / K.fy, 1.0])
    p = np.stack([ray * 2.0, ray * 1.0, ray * 1.5]).astype(np.float32)
    maps = render_index_map(p, np.zeros_like(p), K)
    assert maps.index[50, 100] == 1 and (maps.index >= 0).sum() == 1
    np.testing.assert_array_equal(maps.vertex[50, 100], p[1])


def test_no_surfels_or_all_behind_the_camera_give_empty_maps():
    p, n, _ = random_surfels(5000)
    for pos in (np.zeros((0, 3), np.float32), p * np.float32(-1.0), p * np.float32(0.001),
                p * np.float32(100.0)):   # behind, nearer than near_m, beyond far_m
        for s in (1, 4):
            maps = render_index_map(pos, n[:len(pos)], K, supersample=s)
            assert (maps.index == -1).all()
            assert not maps.vertex.any() and not maps.normal.any()
    # Behind-the-camera points must not leave stale results from an earlier call either.
    render_index_map(p, n, K)
    assert (render_index_map(-p, n, K).index == -1).all()


def test_a_map_after_others_of_other_rows_and_sizes_holds_only_its_own_surfels():
    """The scatter clears and reads only the rows a map's surfels reach: what an earlier map
    wrote elsewhere (other rows, the other supersampling) must be gone."""
    p, n, _ = random_surfels(20_000, seed=7)
    v = K.project(p.astype(np.float64))[:, 1]
    top, bottom = p[v < 150], p[v > 330]
    for s, pos in ((4, top), (1, p), (4, bottom), (1, top), (4, p), (4, bottom[:1]), (4, top)):
        maps = render_index_map(pos, np.zeros_like(pos), K, supersample=s)
        ref = reference_index(pos, K.supersampled(s))
        covered = (ref >= 0) | (maps.index >= 0)
        assert (ref == maps.index)[covered].mean() >= 0.999
        rows = np.flatnonzero((ref >= 0).any(axis=1))
        outside = np.ones(len(ref), bool)
        outside[max(rows[0] - 2, 0):rows[-1] + 3] = False
        assert (maps.index[outside] == -1).all() and maps.index.max() < len(pos)
    # a NaN or infinite point lands nowhere and does not upset the rows
    bad = np.vstack([top[:100], [[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0], [0.0, 1e30, 1e-30 + 1.0]]]).astype(np.float32)
    maps = render_index_map(bad, np.zeros_like(bad), K, supersample=4)
    assert (maps.index >= 0).sum() <= 100 and maps.index.max() < 100
