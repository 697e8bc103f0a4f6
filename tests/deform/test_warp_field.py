import cv2
import numpy as np
import pytest
from scipy.spatial.distance import cdist

from surfelwarp.deform.warp_field import (WarpField, WarpFieldParams, build_graph, extend, inverse_warp, sample_nodes,
                                          skin, to_global, to_local, update_skinning, warp)
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.dual_quaternion import dq_blend, dq_to_transform
from surfelwarp.geometry.se3 import se3_exp

from conftest import shared_data


def bumpy_sheet(step=0.004, half=(0.3, 0.22)):
    """A bumpy 0.6 x 0.44 m sheet 1 m away; jittered so that no two nodes tie in distance."""
    s, t = np.meshgrid(np.arange(-half[0], half[0], step), np.arange(-half[1], half[1], step))
    z = 1.0 + 0.015 * np.sin(2 * np.pi * s / 0.2) * np.cos(2 * np.pi * t / 0.25)
    pts = np.stack([s, t, z], -1).reshape(-1, 3)
    return (pts + np.random.default_rng(7).normal(scale=2e-4, size=pts.shape)).astype(np.float32)


def shirt_points() -> np.ndarray:
    """Frame 0 of the DeepDeform shirt, masked, in metres (camera frame), every other pixel."""
    root = shared_data("deepdeform-shirt-pair")
    K = np.loadtxt(root / "intrinsics.txt")
    intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480)
    depth = cv2.imread(str(root / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000
    mask = cv2.imread(str(root / "mask" / "000000_shirt.png"), cv2.IMREAD_UNCHANGED) > 0
    keep = (depth > 0) & mask
    keep[::2] = False
    keep[:, ::2] = False
    return intr.backproject(depth)[keep]


def smooth_field(field: WarpField, scale=1.0) -> WarpField:
    """A smooth non-rigid motion: node rotations up to ~0.4 rad and cm translations varying in space."""
    p = field.nodes.astype(np.float64)
    xi = np.concatenate([0.4 * scale * np.sin(6 * p[:, [1, 0, 1]] + [0, 1, 2]),
                         0.03 * scale * np.cos(9 * p[:, [0, 1, 0]] + [2, 0, 1])], axis=1)
    return field.with_transforms(se3_exp(xi))


@pytest.mark.parametrize("source", ["sheet", "shirt"])
def test_sampled_nodes_are_spaced_and_cover_every_point(source):
    pts = bumpy_sheet() if source == "sheet" else shirt_points()
    spacing = 0.025
    nodes = sample_nodes(pts, spacing)
    d = cdist(nodes, nodes)
    np.fill_diagonal(d, np.inf)
    cover = cdist(pts, nodes).min(axis=1)
    print(f"{source}: {len(pts)} points -> {len(nodes)} nodes, nearest node spacing "
          f"min {d.min() * 1000:.1f} mean {d.min(1).mean() * 1000:.1f} mm, max point-node {cover.max() * 1000:.1f} mm")
    assert d.min() >= spacing * (1 - 1e-6)
    assert cover.max() <= spacing
    assert d.min(1).mean() < 1.3 * spacing          # not sparser than needed
    # Nodes are points of the input, and sampling is repeatable.
    assert cdist(nodes, pts).min(axis=1).max() < 1e-6
    assert np.array_equal(nodes, sample_nodes(pts, spacing))
    if source == "shirt":
        assert 200 <= len(nodes) <= 1000               # SurfelWarp reports 300-1000 nodes


def test_graph_holds_the_k_nearest_other_nodes():
    nodes = sample_nodes(bumpy_sheet(), 0.025)
    graph = build_graph(nodes, 8)
    assert graph.dtype == np.int32 and graph.shape == (len(nodes), 8)
    d = cdist(nodes, nodes)
    np.fill_diagonal(d, np.inf)
    brute = np.sort(d, axis=1)[:, :8]
    assert np.allclose(np.take_along_axis(d, graph.astype(int), 1), brute)
    # Too few nodes: the missing neighbours are the node itself.
    small = build_graph(nodes[:3], 8)
    assert np.array_equal(small[:, 2:], np.repeat(np.arange(3)[:, None], 6, 1))
    assert np.all(small[:, :2] != np.arange(3)[:, None])
    # Coincident nodes: the tree may list a node after its twin; each keeps the twin, not itself.
    twins = build_graph(np.repeat(nodes[:20], 2, axis=0), 3)
    assert np.all(twins != np.arange(40)[:, None]) and np.array_equal(twins[:, 0], np.arange(40) ^ 1)


def test_skinning_matches_brute_force():
    pts = bumpy_sheet(0.007)
    nodes = sample_nodes(pts, 0.025)
    knn, w = skin(pts, nodes, 4, 0.025)
    assert knn.dtype == np.int32 and w.dtype == np.float32 and knn.shape == w.shape == (len(pts), 4)
    d2 = cdist(pts, nodes, "sqeuclidean")
    order = np.argsort(d2, axis=1)[:, :4]
    assert np.allclose(np.take_along_axis(d2, knn.astype(int), 1), np.take_along_axis(d2, order, 1), atol=1e-9)
    expect = np.exp(-np.take_along_axis(d2, knn.astype(int), 1) / (2 * 0.025 ** 2))
    assert np.allclose(w, expect / expect.sum(1, keepdims=True), atol=1e-6)
    # Two nodes only: the extra slots repeat the nearest with zero weight.
    knn2, w2 = skin(pts, nodes[:2], 4, 0.025)
    assert np.all(knn2[:, 2:] == knn2[:, :1]) and np.all(w2[:, 2:] == 0) and np.allclose(w2.sum(1), 1)


def test_rigid_field_warps_like_the_rigid_transform():
    pts = bumpy_sheet(0.006).astype(np.float64)
    field = WarpField.from_points(pts)
    G = se3_exp(np.array([0.4, -0.9, 0.3, 0.2, 0.05, -0.1]))
    rigid = field.with_transforms(to_local(np.tile(G, (field.num_nodes, 1, 1)), field.nodes))
    assert np.allclose(rigid.global_transforms(), G, atol=1e-12)
    knn, w = skin(pts, field.nodes, 4, field.sigma_m)
    normals = np.random.default_rng(0).normal(size=pts.shape)
    live, live_n = warp(pts, normals, knn, w, rigid)
    assert np.abs(live - (pts @ G[:3, :3].T + G[:3, 3])).max() < 1e-12
    assert np.abs(live_n - normals @ G[:3, :3].T).max() < 1e-12
    # Node-local convention: a node moves by its own translation.
    assert np.allclose(rigid.live_nodes(), field.nodes @ G[:3, :3].T + G[:3, 3], atol=1e-6)


def test_a_fields_dual_quaternions_are_made_once_and_read_only():
    from surfelwarp.geometry.dual_quaternion import dq_from_transform
    field = smooth_field(WarpField.from_points(bumpy_sheet(0.01)))
    dqs = field.dual_quaternions()
    assert dqs.tobytes() == dq_from_transform(field.global_transforms()).tobytes()
    assert field.dual_quaternions() is dqs and not dqs.flags.writeable
    with pytest.raises(ValueError):
        dqs[0, 0] = 2.0
    # a field with other transforms makes its own
    moved = field.with_transforms(field.transforms[::-1].copy())
    assert moved.dual_quaternions() is not dqs
    assert moved.dual_quaternions().tobytes() == dq_from_transform(moved.global_transforms()).tobytes()
    # a checkpoint's copy keeps the field, not the cache
    import pickle
    copy = pickle.loads(pickle.dumps(field))
    assert "_dual_quaternions" not in copy.__dict__ and copy.transforms.tobytes() == field.transforms.tobytes()
    assert copy.dual_quaternions().tobytes() == dqs.tobytes() and not copy.dual_quaternions().flags.writeable


def test_inverse_warp_undoes_warp():
    pts = shirt_points()
    field = smooth_field(WarpField.from_points(pts))
    knn, w = skin(pts, field.nodes, 4, field.sigma_m)
    normals = np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (len(pts), 1))
    live, live_n = warp(pts, normals, knn, w, field)
    assert live.dtype == np.float32
    moved = np.linalg.norm(live - pts, axis=1)
    back, back_n = inverse_warp(live, live_n, knn, w, field)
    err = np.linalg.norm(back - pts, axis=1).max()
    print(f"shirt: warp moved points {moved.mean() * 1000:.1f} mm on average, round trip error {err * 1e6:.2f} um")
    assert moved.mean() > 0.01
    assert err < 2e-6 and np.abs(back_n - normals).max() < 1e-6
    # In float64 the round trip is exact to rounding.
    live64, _ = warp(pts.astype(np.float64), None, knn, w, field)
    back64, _ = inverse_warp(live64, None, knn, w, field)
    assert np.abs(back64 - pts).max() < 1e-12


def test_blend_is_smooth_between_nodes():
    """Points between two nodes move between the nodes' motions (no jump where the nearest node changes)."""
    nodes = np.array([[0.0, 0, 1], [0.05, 0, 1]], np.float32)
    field = WarpField.identity(nodes).with_transforms(se3_exp(np.array([[0, 0, 0, 0, 0, 0], [0, 0, 0.3, 0, 0, 0.02]])))
    x = np.stack([np.linspace(0, 0.05, 101), np.zeros(101), np.ones(101)], 1)
    knn, w = skin(x, nodes, 4, field.sigma_m)
    live, _ = warp(x, None, knn, w, field)
    step = np.linalg.norm(np.diff(live - x, axis=0), axis=1)
    assert step.max() < 3 * step.mean()


def test_extend_covers_new_points_with_the_current_warp():
    pts = bumpy_sheet(0.005)
    left = pts[pts[:, 0] < 0.0]
    field = smooth_field(WarpField.from_points(left))
    new_field, first = extend(field, pts)
    assert first == field.num_nodes and new_field.num_nodes > field.num_nodes
    assert np.array_equal(new_field.nodes[:first], field.nodes)
    assert np.array_equal(new_field.transforms[:first], field.transforms)
    assert new_field.graph.shape == (new_field.num_nodes, 8)
    assert new_field.graph.max() >= first and np.all(new_field.graph != np.arange(new_field.num_nodes)[:, None])
    # Coverage (DynamicFusion Sec. 3.4): every point within sigma of a node.
    cover = cdist(pts, new_field.nodes).min(axis=1)
    assert cover.max() <= new_field.sigma_m
    # New nodes start with DQB of the old field at their position.
    new = new_field.nodes[first:]
    knn, w = skin(new, field.nodes, 4, field.sigma_m)
    G = dq_to_transform(dq_blend(field.dual_quaternions()[knn], w))
    assert np.allclose(to_global(new_field.transforms[first:], new), G, atol=1e-9)
    # Already covered points add nothing.
    same, first_again = extend(new_field, pts)
    assert same is new_field and first_again == new_field.num_nodes
    print(f"extend: {field.num_nodes} -> {new_field.num_nodes} nodes")


def test_extend_of_a_rigid_field_stays_rigid():
    pts = bumpy_sheet(0.005)
    field = WarpField.from_points(pts[pts[:, 1] < 0])
    G = se3_exp(np.array([0.1, 0.2, -0.3, 0.05, 0.0, 0.02]))
    field = field.with_transforms(to_local(np.tile(G, (field.num_nodes, 1, 1)), field.nodes))
    new_field, _ = extend(field, pts)
    assert np.allclose(new_field.global_transforms(), G, atol=1e-9)


@pytest.mark.parametrize("few_new_nodes", [0, 10 ** 6])      # the screen by k-d tree, and by all new nodes
@pytest.mark.parametrize("start_nodes", [2, 0])
def test_update_skinning_equals_skinning_from_scratch(start_nodes, few_new_nodes, monkeypatch):
    import surfelwarp.deform.warp_field as warp_field
    monkeypatch.setattr(warp_field, "_FEW_NEW_NODES", few_new_nodes)
    pts = bumpy_sheet(0.006)
    params = WarpFieldParams()
    if start_nodes:
        field = WarpField.identity(sample_nodes(pts, 0.025)[:start_nodes], params)   # padded skinning
    else:
        field = WarpField.from_points(pts[pts[:, 0] < 0.05], params)
    knn, w = skin(pts, field.nodes, 4, field.sigma_m)
    new_field, first = extend(field, pts)
    knn2, w2 = update_skinning(knn, w, pts, new_field, first)
    ref_knn, ref_w = skin(pts, new_field.nodes, 4, new_field.sigma_m)
    if not start_nodes:
        # Points no new node comes near keep their skinning exactly.
        gap = np.min(np.linalg.norm(pts[:, None] - new_field.nodes[None, first:], axis=-1), axis=1)
        far = gap > 0.1
        assert far.sum() > 1000
        assert np.array_equal(knn2[far], knn[far]) and np.array_equal(w2[far], w[far])
    d2 = np.sum((pts[:, None, :] - new_field.nodes[knn2]) ** 2, -1)
    d2_ref = np.sum((pts[:, None, :] - new_field.nodes[ref_knn]) ** 2, -1)
    assert np.allclose(d2, d2_ref, atol=1e-10)
    assert np.allclose(w2, ref_w, atol=1e-6)
    live, _ = warp(pts, None, knn2, w2, smooth_field(new_field))
    live_ref, _ = warp(pts, None, ref_knn, ref_w, smooth_field(new_field))
    assert np.abs(live - live_ref).max() < 1e-5
