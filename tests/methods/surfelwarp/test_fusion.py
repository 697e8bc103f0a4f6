from dataclasses import replace

import numpy as np
import pytest

from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.methods.surfelwarp import fusion
from surfelwarp.methods.surfelwarp.fusion import (FusionParams, find_correspondences, fuse, removal_mask,
                                                  unmatched_depth_pixels)
from surfelwarp.geometry.se3 import invert, se3_exp, transform_points
from surfelwarp.methods.surfelwarp.surfels import SurfelModel
from surfelwarp.preprocess import preprocess
from surfelwarp.render.index_map import FusionMaps, render_index_map

from conftest import numba_threads, shared_data

K = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
# Camera pose in world: a turn and a shift, so every test also runs the camera->world transform.
T_CAM = se3_exp(np.array([0.1, -0.25, 0.05, 0.3, -0.1, 0.2]))




def scene_depth() -> np.ndarray:
    """A tilted plane at ~1.2 m with a sphere (r 0.2 m) in front: analytic depth in metres."""
    u, v = np.meshgrid((np.arange(K.width) - K.cx) / K.fx, (np.arange(K.height) - K.cy) / K.fy)
    rays = np.stack([u, v, np.ones_like(u)], -1)
    n = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    z_plane = (n @ [0, 0, 1.2]) / (rays @ n)
    unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    centre = np.array([0.05, 0.0, 0.9])
    b = unit @ centre
    disc = b * b - (centre @ centre - 0.2 ** 2)
    z_sphere = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.inf) * unit[..., 2]
    return np.minimum(z_plane, z_sphere).astype(np.float32)


@pytest.fixture(scope="module")
def obs():
    return preprocess(scene_depth(), K, frame_index=0, time=0)


def model_from(obs, confidence=None, time=0) -> SurfelModel:
    """World-frame surfels exactly on the observation's valid pixels, in row-major pixel order."""
    s = obs.surfels()
    conf = s["confidence"] if confidence is None else confidence
    return SurfelModel.from_points(transform_points(T_CAM, s["position"].astype(np.float64)),
                                   s["normal"] @ T_CAM[:3, :3].T, s["radius"], conf, time, 0)


def render(model: SurfelModel) -> FusionMaps:
    T = invert(T_CAM)
    return render_index_map(transform_points(T, model.live_position.astype(np.float64)),
                            model.live_normal @ T[:3, :3].T, K, supersample=4)


def with_live(model, position=None, normal=None) -> SurfelModel:
    position = model.live_position if position is None else np.asarray(position, np.float32)
    normal = model.live_normal if normal is None else np.asarray(normal, np.float32)
    return replace(model, live_position=position, live_normal=normal)


def along_rays(model, offset_m):
    """Live positions pushed away from the camera along their viewing rays."""
    centre = T_CAM[:3, 3]
    ray = model.live_position - centre
    return model.live_position + offset_m * ray / np.linalg.norm(ray, axis=1, keepdims=True)


def tilted(normals, angle_rad):
    """Each normal turned by angle_rad about an axis perpendicular to it."""
    axis = np.cross(normals, [0.0, 0.0, 1.0]) + np.cross(normals, [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    axis -= np.sum(axis * normals, 1, keepdims=True) * normals
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return normals * np.cos(angle_rad) + np.cross(axis, normals) * np.sin(angle_rad)


def test_exact_model_every_pixel_finds_its_own_surfel(gl, obs):
    model = model_from(obs)
    assert obs.num_valid > 12000
    corr = find_correspondences(render(model), obs, model.confidence)
    rows, cols = np.nonzero(obs.valid)
    assert len(corr.surfel_index) == obs.num_valid
    # find_correspondences returns pixels in row-major order, the model's order.
    np.testing.assert_array_equal(corr.pixel_rows, rows)
    np.testing.assert_array_equal(corr.pixel_cols, cols)
    np.testing.assert_array_equal(corr.surfel_index, np.arange(len(model)))
    _, fused = fuse(model, T_CAM, obs, corr, time=1)
    assert not unmatched_depth_pixels(obs, fused).any()


def test_fuse_moves_surfels_toward_depth_by_confidence_weights(gl, obs):
    rng = np.random.default_rng(1)
    base = model_from(obs, confidence=rng.uniform(1, 30, obs.num_valid).astype(np.float32))
    model = with_live(base, along_rays(base, 0.004), tilted(base.live_normal.astype(np.float64), np.deg2rad(20)))
    model = replace(model, radius=model.radius * 1.5)
    corr = find_correspondences(render(model), obs, model.confidence)
    np.testing.assert_array_equal(corr.surfel_index, np.arange(len(model)))

    new, fused = fuse(model, T_CAM, obs, corr, time=7)
    assert fused.sum() == obs.num_valid
    s = obs.surfels()
    c_old, c_depth = model.confidence.astype(np.float64), s["confidence"].astype(np.float64)
    w_old = (c_old / (c_old + c_depth))[:, None]
    depth_v = transform_points(T_CAM, s["position"].astype(np.float64))
    depth_n = s["normal"] @ T_CAM[:3, :3].T
    expected_v = w_old * model.live_position + (1 - w_old) * depth_v
    np.testing.assert_allclose(new.live_position, expected_v, atol=2e-6)
    # The surfel was 4 mm behind the depth point on the same ray: it is now 4 mm * w_old behind.
    np.testing.assert_allclose(np.linalg.norm(new.live_position - depth_v, axis=1), 0.004 * w_old[:, 0], atol=2e-6)
    n = w_old * model.live_normal + (1 - w_old) * depth_n
    np.testing.assert_allclose(new.live_normal, n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(new.live_normal, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(new.radius, w_old[:, 0] * model.radius + (1 - w_old[:, 0]) * s["radius"], rtol=1e-6)
    np.testing.assert_allclose(new.confidence, c_old + c_depth, rtol=1e-6)
    assert (new.t_observed == 7).all() and (new.t_init == 0).all()
    # Only the live geometry moves; the input model is not modified.
    assert new.ref_position is model.ref_position and new.ref_normal is model.ref_normal
    assert not np.shares_memory(new.live_position, model.live_position)
    assert (model.t_observed == 0).all()


def test_only_matched_surfels_change(gl, obs):
    model = model_from(obs)
    drop = np.zeros(len(model), bool)
    drop[::3] = True                      # these surfels are pushed 5 cm away
    model = with_live(model, np.where(drop[:, None], along_rays(model, 0.05), model.live_position))
    corr = find_correspondences(render(model), obs, model.confidence)
    assert set(corr.surfel_index) == set(np.flatnonzero(~drop))
    new, fused = fuse(model, T_CAM, obs, corr, time=3)
    np.testing.assert_array_equal(new.live_position[drop], model.live_position[drop])
    np.testing.assert_array_equal(new.confidence[drop], model.confidence[drop])
    assert (new.t_observed[drop] == 0).all() and (new.t_observed[~drop] == 3).all()
    rows, cols = np.nonzero(obs.valid)
    np.testing.assert_array_equal(unmatched_depth_pixels(obs, fused)[rows, cols], drop)


@pytest.mark.parametrize("offset_m, found", [(0.009, True), (0.011, False), (0.05, False)])
def test_distance_gate(gl, obs, offset_m, found):
    model = model_from(obs)
    model = with_live(model, along_rays(model, offset_m))
    corr = find_correspondences(render(model), obs, model.confidence)
    assert len(corr.surfel_index) == (obs.num_valid if found else 0)


@pytest.mark.parametrize("angle_deg, found", [(30, True), (35, False), (60, False)])
def test_normal_gate(gl, obs, angle_deg, found):
    # cos 30 = 0.866 passes delta_normal = 0.85, cos 35 = 0.819 does not.
    model = model_from(obs)
    model = with_live(model, normal=tilted(model.live_normal.astype(np.float64), np.deg2rad(angle_deg)))
    corr = find_correspondences(render(model), obs, model.confidence)
    assert len(corr.surfel_index) == (obs.num_valid if found else 0)


def test_highest_confidence_then_closest(obs):
    """Hand-made index maps: three candidates in every depth pixel's 4x4 block."""
    rows, cols = np.nonzero(obs.valid)
    p = len(rows)
    v = obs.vertex_map[rows, cols]
    n = obs.normal_map[rows, cols]
    shape = (K.height * 4, K.width * 4)
    index = np.full(shape, -1, np.int32)
    points = np.zeros((3 * p, 3), np.float32)
    # Candidate a: 2 mm off, b: 1 mm off, c: 6 mm off, at three sub-pixels of the block.
    offsets = {0: (0, 0, 0.002), 1: (3, 3, 0.001), 2: (1, 2, 0.006)}
    for slot, (dy, dx, d) in offsets.items():
        index[4 * rows + dy, 4 * cols + dx] = 3 * np.arange(p) + slot
        points[slot::3] = v + d * n
    maps = FusionMaps(index, 4, K.supersampled(4), points, np.repeat(n, 3, axis=0))

    def pick(conf, maps=maps):
        return find_correspondences(maps, obs, np.tile(np.asarray(conf, np.float32), p)).surfel_index % 3

    assert (pick([5, 5, 9]) == 2).all()      # highest confidence wins even farther away
    assert (pick([5, 5, 5]) == 1).all()      # confidence tie: the closest
    assert (pick([6, 5, 5]) == 0).all()
    far = points.copy()
    far[2::3] = v + 0.012 * n
    assert (pick([5, 5, 9], replace(maps, points=far)) == 1).all()   # c beyond 1 cm: b
    # The paper's 1 mm gate leaves only b.
    tight = FusionParams(distance_threshold_m=0.0015)
    assert (find_correspondences(maps, obs, np.full(3 * p, 5, np.float32), tight).surfel_index % 3 == 1).all()


def test_overlapping_windows_give_each_surfel_one_pixel(gl, obs):
    # An 8x8 window reaches into the neighbouring blocks; with every other surfel missing the
    # orphaned pixels reach for their neighbours' surfels and must lose them to the owners.
    model = model_from(obs, confidence=np.full(obs.num_valid, 10, np.float32))
    rows, cols = np.nonzero(obs.valid)
    keep = (rows + cols) % 2 == 0
    model = model.select(keep)
    corr = find_correspondences(render(model), obs, model.confidence, FusionParams(window=8))
    assert len(np.unique(corr.surfel_index)) == len(corr.surfel_index) == len(model)
    owner = np.flatnonzero(keep)[corr.surfel_index]
    np.testing.assert_array_equal(corr.pixel_rows, rows[owner])
    np.testing.assert_array_equal(corr.pixel_cols, cols[owner])


def test_duplicates_are_removed_once(gl, obs):
    rng = np.random.default_rng(2)
    base = model_from(obs, confidence=np.full(obs.num_valid, 20, np.float32))
    params = FusionParams()
    assert not removal_mask(base, render(base), 5, params, T_CAM).any()

    originals = rng.choice(len(base), 300, replace=False)
    dup = base.select(originals)
    step = rng.normal(size=(300, 3))
    step *= 1e-4 / np.linalg.norm(step, axis=1, keepdims=True)        # 0.1 mm away
    confidence = np.where(np.arange(300) < 150, 15, 25).astype(np.float32)
    dup = replace(with_live(dup, dup.live_position + step, tilted(dup.live_normal.astype(np.float64), 0.05)),
                  confidence=confidence)
    model = base.concatenate(dup)
    drop = removal_mask(model, render(model), 5, params, T_CAM)
    assert drop.sum() == 300
    pair_first, pair_second = originals, len(base) + np.arange(300)
    # Of each pair exactly one goes: the duplicate when it is less confident, else the original.
    np.testing.assert_array_equal(drop[pair_second], confidence < 20)
    np.testing.assert_array_equal(drop[pair_first], confidence > 20)
    assert len(fusion.remove(model, drop)) == len(base)

    # Without the pose only pairs that both show on the map are found; still never both.
    visible_only = removal_mask(model, render(model), 5, params)
    assert not (visible_only[pair_first] & visible_only[pair_second]).any()
    assert visible_only.sum() == (visible_only[pair_first] | visible_only[pair_second]).sum()


def test_similar_but_distinct_surfels_are_kept(gl, obs):
    base = model_from(obs)
    params = FusionParams()
    # Surfels of adjacent depth pixels squeezed to 0.6 of the pixel spacing (~5 mm here, inside
    # half a radius): 2.4 fine pixels apart, so not neighbours on the index map.
    s = obs.surfels()
    shift = np.where((s["pixel"][:, 1] % 2 == 0)[:, None], 0.2, -0.2) * np.array([1.0, 0, 0]) / K.fx
    squeezed = with_live(base, transform_points(T_CAM, s["position"] + shift * s["position"][:, 2:3]))
    assert not fusion.redundant_mask(squeezed, render(squeezed), params, T_CAM).any()
    # Copies behind on the same ray (the same fine pixel): 0.6 radius is beyond the gate of half
    # a radius, 0.4 radius is a duplicate. Copies 0.1 mm away with normals 30 deg off (a fold).
    behind = [with_live(base, along_rays(base, ratio * base.radius[:, None])) for ratio in (0.6, 0.4)]
    folded = with_live(base, base.live_position + 1e-4,
                       tilted(base.live_normal.astype(np.float64), np.deg2rad(30)))
    for copy, duplicates in ((behind[0], False), (folded, False), (behind[1], True)):
        model = base.concatenate(copy)
        drop = fusion.redundant_mask(model, render(model), params, T_CAM)
        assert drop.sum() == (len(base) if duplicates else 0)
        # The copies have equal confidence: the higher index (the copy) goes.
        assert not drop[:len(base)].any()


def test_unstable_surfels_removed_after_30_frames(gl, obs):
    model = model_from(obs, confidence=np.full(obs.num_valid, 20, np.float32), time=0)
    rng = np.random.default_rng(3)
    confidence = rng.choice([5.0, 9.9, 10.0, 12.0], len(model)).astype(np.float32)
    t_init = rng.integers(0, 40, len(model)).astype(np.int32)
    model = replace(model, confidence=confidence, t_init=t_init)
    time = 40
    drop = removal_mask(model, render(model), time, FusionParams(), T_CAM)
    expected = (confidence < 10) & (time - t_init > 30)
    np.testing.assert_array_equal(drop, expected)
    assert expected.sum() > 1000 and ((confidence < 10) & ~expected).sum() > 1000   # both kinds occur
    assert len(fusion.remove(model, drop)) == len(model) - expected.sum()


def test_real_frames_need_a_gate_wider_than_1mm(gl):
    """7-Scenes frames 0 and 5 with the ground-truth poses: 1 cm fuses most pixels, 1 mm few;
    widening the gate with the sensor noise at 1-3 m fuses more than 1 cm alone."""
    root = shared_data("rigid-7scenes")
    from surfelwarp.io.sequence import open_sequence
    seq = open_sequence(root, max_frames=6)
    frames = list(seq.frames())
    first, last = frames[0], frames[5]
    intr = seq.intrinsics
    obs0 = preprocess(first[1], intr, first[0].index, 0)
    obs5 = preprocess(last[1], intr, last[0].index, 5)
    s = obs0.surfels()
    model = SurfelModel.from_points(s["position"], s["normal"], s["radius"], s["confidence"], 0, 0)
    T_5_to_0 = invert(seq.read_pose(first[0])) @ seq.read_pose(last[0])
    T = invert(T_5_to_0)
    maps = render_index_map(transform_points(T, model.live_position.astype(np.float64)),
                            model.live_normal @ T[:3, :3].T, intr, supersample=4)
    gates = {0.001: FusionParams(distance_threshold_m=0.001, distance_noise_sigmas=0),
             0.01: FusionParams(distance_threshold_m=0.01, distance_noise_sigmas=0), "noise": FusionParams()}
    share = {gate: len(find_correspondences(maps, obs5, model.confidence, params)[0]) / obs5.num_valid
             for gate, params in gates.items()}
    assert share[0.01] > 0.7 and share[0.001] < 0.2 and share["noise"] > share[0.01] + 0.02, share


def test_distance_gate_follows_the_axial_noise():
    params = FusionParams()
    gate = fusion.distance_gate_m(np.array([0.5, 0.85, 1.5, 2.5]), params)
    sigma = 0.0012 + 0.0019 * (np.array([1.5, 2.5]) - 0.4) ** 2
    np.testing.assert_allclose(gate, [0.01, 0.01, *(3 * sigma)], rtol=1e-6)
    assert (fusion.distance_gate_m(np.array([2.5]), FusionParams(distance_noise_sigmas=0)) == np.float32(0.01)).all()


def test_covered_pixels_are_not_appended(gl, obs):
    """A depth pixel whose own surfel fails the normal gate, or whose surfel sits one pixel
    over, is covered: not new surface. A surfel facing the other way (the back of a thin
    object) or beyond the distance gate does not cover it."""
    model = model_from(obs)
    nothing = np.zeros(obs.valid.shape, bool)
    steep = with_live(model, normal=tilted(model.live_normal.astype(np.float64), np.deg2rad(60)))
    maps = render(steep)
    assert len(find_correspondences(maps, obs, steep.confidence).surfel_index) == 0
    assert not unmatched_depth_pixels(obs, nothing, maps).any()
    assert unmatched_depth_pixels(obs, nothing).sum() == obs.num_valid          # without the maps: all
    back = with_live(model, normal=-model.live_normal)
    assert unmatched_depth_pixels(obs, nothing, render(back)).sum() > 0.99 * obs.num_valid
    far = with_live(model, along_rays(model, 0.05))
    assert unmatched_depth_pixels(obs, nothing, render(far)).sum() > 0.99 * obs.num_valid
    # Every other surfel dropped (a stretched model): the neighbours' surfels cover the gaps;
    # with coverage_px = 0 only a pixel's own surfels count.
    sparse = model.select(np.arange(len(model)) % 2 == 0)
    corr = find_correspondences(render(sparse), obs, sparse.confidence)
    _, fused = fuse(sparse, T_CAM, obs, corr, time=1)
    assert unmatched_depth_pixels(obs, fused).sum() > 0.3 * obs.num_valid
    assert unmatched_depth_pixels(obs, fused, render(sparse)).sum() < 0.02 * obs.num_valid
    own = unmatched_depth_pixels(obs, fused, render(sparse), FusionParams(coverage_px=0))
    assert own.sum() > 0.3 * obs.num_valid


def unmatched_reference(obs, fused_pixel_mask, maps, params=FusionParams()):
    """unmatched_depth_pixels as whole-array numpy passes, one a neighbour offset."""
    unmatched = obs.valid & ~fused_pixel_mask
    rows, cols = np.nonzero(unmatched)
    s, c = maps.supersample, params.coverage_px
    h, w = unmatched.shape
    depth_v, depth_n = obs.vertex_map[rows, cols], obs.normal_map[rows, cols]
    z = obs.depth_m[rows, cols]
    max_d2 = (fusion.distance_gate_m(z, params) + np.sqrt(2) * params.coverage_px * z / obs.intrinsics.focal_px) ** 2
    blocks = maps.index.reshape(h, s, w, s)
    covered = np.zeros(len(rows), bool)
    for dy in range(-c, c + 1):
        for dx in range(-c, c + 1):
            open_ = np.flatnonzero(~covered & (rows + dy >= 0) & (rows + dy < h) & (cols + dx >= 0) & (cols + dx < w))
            k = blocks[rows[open_] + dy, :, cols[open_] + dx, :].reshape(len(open_), s * s)
            pix, slot = np.nonzero(k >= 0)
            kc, pix = k[pix, slot], open_[pix]
            diff = maps.points[kc] - depth_v[pix]
            near = np.einsum("ij,ij->i", diff, diff) <= max_d2[pix]
            same_side = np.einsum("ij,ij->i", maps.normals[kc], depth_n[pix]) > 0
            covered[pix[near & same_side]] = True
    unmatched[rows[covered], cols[covered]] = False
    return unmatched


def test_compiled_coverage_equals_the_numpy_passes(gl, obs):
    """The compiled coverage search against the numpy passes it replaced, on models that cover
    all, some or none of the pixels (shifted along the rays by about the gate, turned, thinned,
    facing away), coverage 0-2 pixels."""
    model = model_from(obs)
    rng = np.random.default_rng(3)
    fused = rng.random(obs.valid.shape) < 0.3
    models = [model, model.select(np.arange(len(model)) % 3 == 0), with_live(model, normal=-model.live_normal),
              with_live(model, along_rays(model, 0.012)), with_live(model, along_rays(model, -0.02)),
              with_live(model, normal=tilted(model.live_normal.astype(np.float64), np.deg2rad(80)))]
    counts = []
    for m in models:
        for coverage in (0, 1, 2):
            params = FusionParams(coverage_px=coverage)
            expected = unmatched_reference(obs, fused, render(m), params)
            assert np.array_equal(unmatched_depth_pixels(obs, fused, render(m), params), expected)
            counts.append(int(expected.sum()))
    assert min(counts) < 0.05 * obs.num_valid and max(counts) > 0.6 * obs.num_valid, counts


def random_search_inputs(rng, n: int, h: int, w: int, s: int, fill: float, pixel_share: float, spread_m: float):
    """Inputs of fusion's index-map searches: a fine map (h, w) of n surfels on a share `fill`
    of its pixels, their points (spread_m apart), normals about -z and confidences 0-2 (ties),
    and the depth pixels of a share pixel_share of the coarse grid (every s-th fine pixel) with
    their vertices and normals (rows, cols, vertex, normal)."""
    index = np.where(rng.random((h, w)) < fill, rng.integers(0, n, (h, w)), -1).astype(np.int32)
    points = rng.normal(scale=spread_m, size=(n, 3)).astype(np.float32)
    normals = np.tile(np.float32([0, 0, -1]), (n, 1)) + rng.normal(scale=0.2, size=(n, 3)).astype(np.float32)
    conf = rng.integers(0, 3, n).astype(np.float32)
    rows, cols = np.nonzero(rng.random((h // s, w // s)) < pixel_share)
    vertex = rng.normal(scale=spread_m, size=(len(rows), 3)).astype(np.float32)
    normal = np.tile(np.float32([0, 0, -1]), (len(rows), 1))
    return index, points, normals, conf, rows, cols, vertex, normal


def test_compiled_searches_equal_a_per_pixel_reference():
    """The compiled window search and duplicate marking against plain loops over a random
    index map with ties in confidence (the order rules decide)."""
    from surfelwarp.methods.surfelwarp.fusion_kernels import best_in_windows, mark_redundant
    rng = np.random.default_rng(9)
    n, h, w, window = 400, 24, 32, 4
    index, points, normals, conf, rows, cols, vertex, normal = random_search_inputs(rng, n, h, w, 4, 0.6, 0.8, 0.01)
    o_r, o_c = 4 * rows - 1, 4 * cols - 1                  # windows reaching over the map's edge
    gate2 = np.full(len(rows), 0.015 ** 2, np.float32)
    best_k, best_d2 = np.empty(len(rows), np.int64), np.empty(len(rows), np.float32)
    best_in_windows(index, o_r, o_c, window + 2, points, normals, vertex, normal, gate2, np.float32(0.9), conf,
                    best_k, best_d2)
    for p in range(len(rows)):
        cands = []
        for dy in range(window + 2):
            for dx in range(window + 2):
                y, x = o_r[p] + dy, o_c[p] + dx
                if 0 <= y < h and 0 <= x < w and index[y, x] >= 0:
                    k = index[y, x]
                    d2 = np.sum((points[k] - vertex[p]) ** 2)
                    if d2 <= gate2[p] and normals[k] @ normal[p] >= np.float32(0.9):
                        cands.append((-conf[k], d2, len(cands), k))
        assert best_k[p] == (min(cands)[3] if cands else -1)
    radius = rng.uniform(0.005, 0.02, n).astype(np.float32)
    fr, fc = np.nonzero(index >= 0)
    drop = np.zeros(n, bool)
    mark_redundant(index, index[fr, fc].astype(np.int64), fr, fc, 1, points, normals, radius, conf,
                   np.float32(0.5), np.float32(0.95), drop)
    expected = np.zeros(n, bool)
    for j, y0, x0 in zip(index[fr, fc], fr, fc):
        for y in range(max(y0 - 1, 0), min(y0 + 2, h)):
            for x in range(max(x0 - 1, 0), min(x0 + 2, w)):
                i = index[y, x]
                if i < 0 or i == j:
                    continue
                limit = np.float32(0.5) * min(radius[i], radius[j])
                if np.sum((points[j] - points[i]) ** 2) < limit * limit and normals[j] @ normals[i] > np.float32(0.95):
                    expected[j if conf[j] < conf[i] or (conf[j] == conf[i] and j > i) else i] = True
    assert drop.any() and np.array_equal(drop, expected)


def test_compiled_searches_do_not_depend_on_the_thread_count():
    """The window search, the duplicate marking and the coverage search, on one thread and on
    two, over random maps where many pixels and surfels compete (the surfels shuffled, so that
    both threads' halves reach the same pixels): the same answers."""
    from surfelwarp.methods.surfelwarp.fusion_kernels import best_in_windows, mark_covered, mark_redundant
    rng = np.random.default_rng(11)
    n, h, w, s = 3000, 96, 128, 4
    index, points, normals, conf, rows, cols, vertex, normal = random_search_inputs(rng, n, h, w, s, 0.8, 0.9, 0.004)
    radius = rng.uniform(0.005, 0.02, n).astype(np.float32)
    gate2 = np.full(len(rows), 0.006 ** 2, np.float32)
    fr, fc = np.nonzero(index >= 0)
    order = rng.permutation(len(fr))          # the surfels in no spatial order: the threads' halves meet
    fr, fc = fr[order], fc[order]

    def answers():
        best_k, best_d2 = np.empty(len(rows), np.int64), np.empty(len(rows), np.float32)
        best_in_windows(index, s * rows - 1, s * cols - 1, s + 2, points, normals, vertex, normal, gate2,
                        np.float32(0.9), conf, best_k, best_d2)
        drop = np.zeros(n, bool)
        mark_redundant(index, index[fr, fc].astype(np.int64), fr, fc, 1, points, normals, radius, conf,
                       np.float32(0.5), np.float32(0.95), drop)
        covered = np.zeros(len(rows), bool)
        mark_covered(index, s, rows, cols, 1, points, normals, vertex, normal, gate2, covered)
        return best_k, best_d2, drop, covered

    with numba_threads(1):
        one = answers()
    with numba_threads(2):
        two = answers()
    assert (one[0] >= 0).any() and one[2].any() and one[3].any() and not one[3].all()
    for a, b in zip(one, two):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("colour", [False, True])
def test_compiled_fuse_equals_the_numpy_reference(gl, obs, colour):
    """Random confidences, colours and colour weights (some surfels never seen in colour), half
    the surfels matched: the compiled fuse gives fuse_reference's model to the bit."""
    from dataclasses import fields

    from surfelwarp.methods.surfelwarp.fusion import Correspondences, fuse_reference
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (K.height, K.width, 3), dtype=np.uint8)
    seen = replace(obs, color=image) if colour else obs
    base = model_from(obs, confidence=rng.uniform(0.5, 30, obs.num_valid).astype(np.float32))
    model = with_live(base, along_rays(base, 0.003), tilted(base.live_normal.astype(np.float64), np.deg2rad(15)))
    model = replace(model, color=rng.uniform(0, 255, (len(model), 3)).astype(np.float32),
                    color_weight=np.where(rng.random(len(model)) < 0.3, 0, rng.uniform(1, 20, len(model)))
                    .astype(np.float32))
    rows, cols = np.nonzero(obs.valid)
    pick = np.sort(rng.choice(len(rows), len(rows) // 2, replace=False))
    corr = Correspondences(rows[pick], cols[pick], rng.permutation(len(model))[: len(pick)].astype(np.int64))
    new, fused = fuse(model, T_CAM, seen, corr, time=5)
    ref, ref_fused = fuse_reference(model, T_CAM, seen, corr, time=5)
    assert np.array_equal(fused, ref_fused) and fused.sum() == len(pick)
    for f in fields(new):
        got, want = getattr(new, f.name), getattr(ref, f.name)
        assert got.dtype == want.dtype and np.array_equal(got, want), f.name
    assert not np.array_equal(new.color, model.color) if colour else new.color is model.color


def test_one_copy_of_the_kept_surfels_then_the_new_ones(obs):
    """select_then (the frame's removal and appending at once) is select, then concatenate."""
    from dataclasses import fields
    rng = np.random.default_rng(2)
    model = model_from(obs, confidence=rng.uniform(1, 9, obs.num_valid).astype(np.float32))
    new = model_from(obs, time=3).select(rng.choice(len(model), 50, replace=False))
    # a mask, sorted rows, rows in any order (kept in that order), none kept
    for keep in (rng.random(len(model)) < 0.7, np.flatnonzero(rng.random(len(model)) < 0.2),
                 rng.permutation(len(model))[:100], np.zeros(len(model), bool)):
        got, want = model.select_then(keep, new), model.select(keep).concatenate(new)
        assert len(got) == len(want) == (keep.sum() if keep.dtype == bool else len(keep)) + len(new)
        for f in fields(got):
            a, b = getattr(got, f.name), getattr(want, f.name)
            assert a.dtype == b.dtype and np.array_equal(a, b), f.name
    with pytest.raises(IndexError):
        model.select_then(np.array([0, len(model)]), new)
