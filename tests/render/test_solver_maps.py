import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.render.solver_maps import render_solver_maps

K = Intrinsics(300.0, 310.0, 159.5, 119.5, 320, 240)


pytestmark = pytest.mark.usefixtures("gl")     # every test here renders


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


TILE_PX = 16      # the reference's pixels are taken a tile at a time, with the disks near it


def reference(p, n, r, intr, rim_px=0.5, min_cos=0.1):
    """Per pixel centre ray: the nearest disk hit (float64). Also a mask of unreliable pixels: near
    the rim of a disk at or in front of the winner, nearly edge-on there, or a depth near-tie; and
    a mask of pixels whose ray meets two or more disks. A disk is tried on the pixels within
    `reach` of its projected centre, 5x its projected radius and 15 px more: far beyond what it
    covers (the same hits as trying every disk on every pixel, on every input here), and no
    grazing ray far from a disk makes a pixel unsure (all pairs: 30 s for 4000 disks)."""
    p, n, r = (np.asarray(a, np.float64) for a in (p, n, r))
    z = p[:, 2]
    centre = np.stack([intr.fx * p[:, 0] / z + intr.cx, intr.fy * p[:, 1] / z + intr.cy], 1)
    reach = 5 * r * intr.focal_px / np.maximum(z - r, 1e-3) + 15
    shape = (intr.height, intr.width)
    out = np.full(shape, -1), np.zeros(shape, bool), np.zeros(shape, bool)
    for v0 in range(0, intr.height, TILE_PX):
        for u0 in range(0, intr.width, TILE_PX):
            v, u = (a.reshape(-1, 1) for a in np.mgrid[v0:min(v0 + TILE_PX, intr.height),
                                                       u0:min(u0 + TILE_PX, intr.width)])
            mid = np.array([u0, v0]) + TILE_PX / 2
            (idx,) = np.nonzero(np.abs(centre - mid).max(1) <= reach + TILE_PX)
            near = np.maximum(np.abs(u - centre[idx, 0]), np.abs(v - centre[idx, 1])) <= reach[idx]
            ref, unsure, multi = _nearest_hits(p[idx], n[idx], r[idx], intr, (u - intr.cx) / intr.fx,
                                               (v - intr.cy) / intr.fy, near, rim_px, min_cos)
            out[0][v, u] = np.append(idx, -1)[ref][:, None]       # -1 (no disk) stays -1
            out[1][v, u] = unsure[:, None]
            out[2][v, u] = multi[:, None]
    return out


def _nearest_hits(p, n, r, intr, dx, dy, near, rim_px, min_cos):
    """reference() on the rays (dx, dy, 1) (pixels, 1) and the disks, pairs not `near` left out
    of the rim test."""
    dd = dx * dx + dy * dy + 1.0
    dn = dx * n[:, 0] + dy * n[:, 1] + n[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p * n).sum(1) / dn                      # (pixels, disks) intersection depth
        dist2 = t * t * dd - 2 * t * (dx * p[:, 0] + dy * p[:, 1] + p[:, 2]) + (p * p).sum(1)
        dist = np.sqrt(np.maximum(dist2, 0.0))
        hit = (t > 0) & (dist <= r)
        depth = np.pad(np.where(hit, t, np.inf), ((0, 0), (0, 2)), constant_values=np.inf)  # 2 disks at least
        two = np.argsort(depth, axis=1)[:, :2]
        best = np.take_along_axis(depth, two, 1)
        cos = np.abs(dn) / np.sqrt(dd)
        footprint = t / intr.focal_px / np.maximum(cos, 1e-6)   # metres per pixel on the disk
        relevant = near & (t > 0) & (t <= best[:, :1] + 1e-6)
        unsure = (relevant & ((np.abs(dist - r) < rim_px * footprint)
                              | (hit & (cos < min_cos)))).any(1)
        unsure |= best[:, 1] - best[:, 0] < 1e-5
    return np.where(np.isfinite(best[:, 0]), two[:, 0], -1), unsure, hit.sum(1) >= 2


def scene(seed=3):
    """A few hundred mostly camera-facing disks, plus a tilted disk crossing a fronto-parallel one
    (so the winner changes inside the overlap) and a disk near grazing incidence."""
    rng = np.random.default_rng(seed)
    m = 300
    z = rng.uniform(0.7, 2.0, m)
    u = rng.uniform(0, K.width, m)
    v = rng.uniform(0, K.height, m)
    p = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1)
    n = unit(-unit(p) + rng.normal(scale=0.4, size=(m, 3)))
    r = rng.uniform(0.01, 0.03, m)
    extra_p = [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.25, -0.15, 1.2]]
    extra_n = [[0.0, 0.0, -1.0], unit([np.sin(1.2), 0.0, -np.cos(1.2)]),   # tilted 69 degrees
               unit(np.cross([0.25, -0.15, 1.2], [0.0, 1.0, 0.0]) + [0.0, 0.0, -0.05])]
    p = np.vstack([p, extra_p]).astype(np.float32)
    n = np.vstack([n, extra_n]).astype(np.float32)
    r = np.r_[r, 0.08, 0.07, 0.05].astype(np.float32)
    return p, n, r


@pytest.mark.parametrize("groups_x", [None, 3])     # 3: the work groups on a 2-D grid, as past 4.2M surfels
def test_solver_maps_match_ray_disk_reference(groups_x, monkeypatch):
    if groups_x:
        monkeypatch.setattr("surfelwarp.render.scatter.MAX_GROUPS_X", groups_x)
    p, n, r = scene()
    maps = render_solver_maps(p, n, r, K)
    assert maps.index.shape == (K.height, K.width) and maps.index.dtype == np.int32
    assert maps.vertex.shape == (K.height, K.width, 3) and maps.intrinsics == K
    ref, unsure, overlap = reference(p, n, r, K)
    covered = ref >= 0
    checked = covered & ~unsure
    assert checked.sum() > 0.6 * covered.sum()
    agree = (maps.index == ref)[checked].mean()
    assert agree >= 0.99, agree
    # Plenty of the checked pixels see two or more disks, so the per-pixel depth test matters.
    assert (checked & overlap).sum() > 2000
    assert (maps.index == ref)[checked & overlap].mean() >= 0.99
    # The tilted disk and the fronto-parallel one cross: each wins on its own side.
    a, b = len(p) - 3, len(p) - 2
    row = int(round(K.cy))
    cols = np.arange(int(K.cx) - 6, int(K.cx) + 16)   # the tilted disk spans about +-7.6 px
    line = maps.index[row, cols]
    assert (line[cols < K.cx - 2] == b).all() and (line[cols > K.cx + 2] == a).all()
    assert (maps.index[(ref == -1) & ~unsure] == -1).all()
    hit = maps.index >= 0
    np.testing.assert_array_equal(maps.vertex[hit], p[maps.index[hit]])
    np.testing.assert_array_equal(maps.normal[hit], n[maps.index[hit]])
    assert not maps.vertex[~hit].any()


def small_disks(m, seed):
    """m disks 0.6-3 px in radius anywhere in view, 0.6-1.5 m away, mostly facing the camera."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.6, 1.5, m)
    u, v = rng.uniform(0, K.width, m), rng.uniform(0, K.height, m)
    p = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], 1).astype(np.float32)
    n = unit(-unit(p) + rng.normal(scale=0.3, size=(m, 3))).astype(np.float32)
    r = (rng.uniform(0.6, 3.0, m) * z / K.fx).astype(np.float32)
    return p, n, r


def test_small_disks_match_the_reference():
    """Disks 0.6-3 px in radius, as a model's surfels are: each pixel whose ray meets one is found
    (the pixels tried about a disk barely exceed its projection), and no other."""
    p, n, r = small_disks(4000, seed=11)
    maps = render_solver_maps(p, n, r, K)
    ref, unsure, _ = reference(p, n, r, K)
    checked = ~unsure
    assert ((ref >= 0) & checked).sum() > 12000
    assert (maps.index == ref)[checked].mean() >= 0.999
    # On the rims too: as many pixels covered as rays meet a disk.
    covered, expected = (maps.index >= 0).sum(), (ref >= 0).sum()
    assert abs(covered / expected - 1) < 0.002, (covered, expected)


def test_disks_cut_to_a_pixel_radius_are_the_reference_of_the_cut_disks():
    """max_radius_px cuts each disk to that many pixels at its centre's depth: the maps are the
    reference's for radii min(r, max_radius_px z / fx); disks within it are drawn as they are."""
    p, n, r = scene()
    cut = np.minimum(r, 3.0 * p[:, 2] / K.fx).astype(np.float32)
    assert (cut < r).mean() > 0.7
    maps = render_solver_maps(p, n, r, K, max_radius_px=3.0)
    ref, unsure, _ = reference(p, n, cut, K)
    checked = (ref >= 0) & ~unsure
    assert checked.sum() > 4000
    assert (maps.index == ref)[checked].mean() >= 0.99
    assert (maps.index[(ref == -1) & ~unsure] == -1).all()
    covered, expected = (maps.index >= 0).sum(), (ref >= 0).sum()
    assert abs(covered / expected - 1) < 0.005, (covered, expected)
    assert (maps.index >= 0).sum() < 0.7 * (render_solver_maps(p, n, r, K).index >= 0).sum()
    small = small_disks(2000, seed=14)
    assert np.array_equal(render_solver_maps(*small, K, max_radius_px=3.5).index,
                          render_solver_maps(*small, K).index)


def test_equal_depths_go_to_the_lowest_index_whatever_the_order_drawn():
    """Every disk twice, drawn in reverse order (the higher copy first): each pixel goes to the
    lower copy, on every pixel the disk wins. The second pass tries only the pixels a surfel
    could win in the first, so a copy that finds its own key already there must still try them."""
    m = 3000
    p, n, r = small_disks(m, seed=12)
    once = render_solver_maps(p, n, r, K).index
    twice = render_solver_maps(np.tile(p, (2, 1)), np.tile(n, (2, 1)), np.tile(r, 2), K,
                               indices=np.arange(2 * m)[::-1]).index
    assert (once >= 0).sum() > 20000
    assert np.array_equal(twice, once)


def test_selected_surfels_keep_full_array_indices():
    p, n, r = scene(seed=4)
    chosen = np.flatnonzero(np.arange(len(p)) % 3 != 1)
    maps = render_solver_maps(p, n, r, K, indices=chosen)
    ref, unsure, _ = reference(p[chosen], n[chosen], r[chosen], K)
    ref = np.where(ref >= 0, chosen[np.maximum(ref, 0)], -1)
    checked = (ref >= 0) & ~unsure
    assert (maps.index == ref)[checked].mean() >= 0.99
    assert np.isin(maps.index[maps.index >= 0], chosen).all()
    assert (render_solver_maps(p, n, r, K, indices=np.array([], int)).index == -1).all()


def test_fill_surfels_show_only_where_the_first_set_leaves_pixels_empty():
    p, n, r = scene(seed=5)
    first = np.flatnonzero(np.arange(len(p)) % 2 == 0)
    fill = np.flatnonzero(np.arange(len(p)) % 2 == 1)
    maps = render_solver_maps(p, n, r, K, indices=first, fill_indices=fill)
    ref_first, unsure_first, _ = reference(p[first], n[first], r[first], K)
    ref_fill, unsure_fill, _ = reference(p[fill], n[fill], r[fill], K)
    ref = np.where(ref_first >= 0, first[np.maximum(ref_first, 0)],
                   np.where(ref_fill >= 0, fill[np.maximum(ref_fill, 0)], -1))
    checked = (ref >= 0) & ~unsure_first & ~(unsure_fill & (ref_first < 0))
    assert (maps.index == ref)[checked].mean() >= 0.99
    # The fill set would win the depth test on many of the first set's pixels, and does not.
    both = render_solver_maps(p, n, r, K, indices=np.concatenate([first, fill]))
    occluded = (ref_first >= 0) & np.isin(both.index, fill) & ~unsure_first
    assert occluded.sum() > 500
    assert np.isin(maps.index[occluded], first).all()
    assert np.isin(maps.index[(ref_first < 0) & (ref_fill >= 0) & ~unsure_fill], fill).mean() >= 0.99


@pytest.mark.parametrize("centre_uv", [(159.5, 119.5), (60.0, 200.0)])
def test_fronto_parallel_disk_area(centre_uv):
    z, radius = 1.3, 0.06
    p = np.array([[(centre_uv[0] - K.cx) / K.fx * z, (centre_uv[1] - K.cy) / K.fy * z, z]])
    maps = render_solver_maps(p, [[0.0, 0.0, -1.0]], [radius], K)
    expected = np.pi * radius ** 2 * K.fx * K.fy / z ** 2
    covered = (maps.index == 0).sum()
    assert abs(covered / expected - 1) < 0.03, (covered, expected)
    # Centred where it should be (row 0 = top).
    vv, uu = np.nonzero(maps.index == 0)
    assert abs(uu.mean() - centre_uv[0]) < 0.5 and abs(vv.mean() - centre_uv[1]) < 0.5


def test_grazing_disks_stay_bounded():
    # Edge-on (its plane holds the camera centre) and 0.5 degrees off edge-on, between a wall
    # behind and, in a second render, a wall in front.
    c = np.array([0.1, 0.05, 1.0])
    edge = unit(np.cross(c, [0.0, 1.0, 0.0]))
    near_edge = unit(edge + 0.009 * unit(-c))
    wall_back = [[0.1, 0.05, 1.2], [0.0, 0.0, -1.0]]
    wall_front = [[0.1, 0.05, 0.9], [0.0, 0.0, -1.0]]
    for disk_n in (edge, near_edge):
        p = np.array([c, wall_back[0]])
        maps = render_solver_maps(p, np.array([disk_n, wall_back[1]]), [0.05, 0.2], K)
        strip = maps.index == 0
        diameter_px = 2 * 0.05 * K.fx / c[2]
        assert strip.sum() <= 2 * diameter_px           # a thin strip at most
        assert (maps.index >= 0).sum() > 0.95 * np.pi * (0.2 * K.fx / 1.2) ** 2 * K.fy / K.fx
        p = np.array([c, wall_front[0]])
        maps = render_solver_maps(p, np.array([disk_n, wall_front[1]]), [0.05, 0.2], K)
        assert not (maps.index == 0).any()              # hidden behind the nearer wall


def test_no_surfels_or_all_behind_the_camera_give_empty_maps():
    p, n, r = scene()
    for pos in (np.zeros((0, 3)), -p, p * 1e-3):
        maps = render_solver_maps(pos, n[:len(pos)], r[:len(pos)], K)
        assert (maps.index == -1).all() and not maps.vertex.any() and not maps.normal.any()


def test_images_wider_than_the_packed_pixel_boxes_are_refused():
    p, n, r = scene()
    with pytest.raises(ValueError, match="32767 pixels a side"):
        render_solver_maps(p, n, r, Intrinsics(300.0, 300.0, 20000.0, 119.5, 40000, 240))


def test_maps_to_world_moves_the_drawn_pixels_and_leaves_the_rest_zero():
    from surfelwarp.geometry.se3 import se3_exp
    from surfelwarp.render.solver_maps import SolverMaps, maps_to_world
    rng = np.random.default_rng(13)
    index = np.where(rng.random((K.height, K.width)) < 0.6, 7, -1).astype(np.int32)
    drawn = index >= 0
    vertex = np.where(drawn[..., None], rng.normal(size=(K.height, K.width, 3)), 0).astype(np.float32)
    normal = np.where(drawn[..., None], unit(rng.normal(size=(K.height, K.width, 3))), 0).astype(np.float32)
    T = se3_exp(np.array([0.3, -0.2, 0.5, 0.1, 2.0, -1.0]))
    world_vertex, world_normal = maps_to_world(SolverMaps(index, vertex, normal, K), T)
    np.testing.assert_allclose(world_vertex[drawn], vertex[drawn] @ T[:3, :3].T + T[:3, 3], atol=1e-5)
    np.testing.assert_allclose(world_normal[drawn], normal[drawn] @ T[:3, :3].T, atol=1e-6)
    assert not world_vertex[~drawn].any() and not world_normal[~drawn].any()
    # The same bits as numpy's product a row at a time and the shift added where drawn (on
    # empty pixels given negative zeros).
    vertex[~drawn] = -0.0
    world_vertex, world_normal = maps_to_world(SolverMaps(index, vertex, normal, K), T)
    R = np.ascontiguousarray(T[:3, :3].T, np.float32)
    expected = vertex @ R
    for i in range(3):
        expected[..., i] += np.float32(T[i, 3]) * drawn.astype(np.float32)
    assert world_vertex.tobytes() == expected.tobytes() and world_normal.tobytes() == (normal @ R).tobytes()


def test_drawn_rows_are_the_world_rows_of_the_drawn_surfels():
    """The solver maps in world from the drawn surfels' own world rows: exactly those rows where
    a surfel shows, zeros elsewhere, and maps_to_world's maps to float32 rounding."""
    from surfelwarp.geometry.se3 import invert, se3_exp, transform_surfels
    from surfelwarp.render.solver_maps import drawn_rows, maps_to_world
    p, n, r = scene()
    T = se3_exp(np.array([0.2, -0.1, 0.3, 0.5, -1.0, 2.0]))
    world_p, world_n = transform_surfels(T, p, n)
    maps = render_solver_maps(*transform_surfels(invert(T), world_p, world_n), r, K)
    drawn = maps.index >= 0
    assert 0.2 < drawn.mean() < 0.9
    vertex, normal = drawn_rows(maps.index, world_p, world_n)
    assert vertex.dtype == normal.dtype == np.float32 and vertex.shape == maps.vertex.shape
    assert np.array_equal(vertex[drawn], world_p[maps.index[drawn]])
    assert np.array_equal(normal[drawn], world_n[maps.index[drawn]])
    assert not vertex[~drawn].any() and not normal[~drawn].any()
    moved_vertex, moved_normal = maps_to_world(maps, T)
    np.testing.assert_allclose(vertex, moved_vertex, atol=2e-6)
    np.testing.assert_allclose(normal, moved_normal, atol=2e-6)
