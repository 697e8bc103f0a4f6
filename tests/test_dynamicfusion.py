import json
from dataclasses import replace

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from surfelwarp.data_tools import synth
from surfelwarp.data_tools.evaluate import evaluate
from surfelwarp.data_tools.geometry import TriangleMesh
from surfelwarp.dynamicfusion import (DynamicFusionMethod, DynamicFusionParams, build_hierarchy, warp_transforms_at,
                                      with_hierarchy)
from surfelwarp.ply import VERTEX_FIELDS, read_ply
from surfelwarp.run import run_sequence
from surfelwarp.sequence import open_sequence
from surfelwarp.tsdf import TSDFParams, node_distance_weight
from surfelwarp.warp_field import WarpField, skin, warp

# 8 mm voxels (3 voxels of truncation, as the 4 mm default) keep the volumes small for tests.
FAST = DynamicFusionParams(tsdf=TSDFParams(voxel_size_m=0.008, truncation_m=0.024))
STAGES = {"solver_maps", "rigid", "nonrigid", "warp", "fusion", "marching_cubes", "extend", "warp_mesh"}


def run_df(seq_dir, out, params=FAST, frames=None, save_every=4):
    seq = open_sequence(seq_dir, max_frames=frames)
    method = DynamicFusionMethod(seq.intrinsics, params)
    run_sequence(seq, out, method, save_every=save_every, progress=False)
    return method, json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    return synth.generate("sheet", tmp_path_factory.mktemp("seq") / "sheet", frames=8, size=(320, 240))


def test_sheet_run_writes_the_contract_and_tracks_the_surface(sheet, tmp_path):
    out = tmp_path / "df"
    method, metrics = run_df(sheet, out)
    assert metrics["method"] == "dynamicfusion" and metrics["config"]["method"]["tsdf"]["voxel_size_m"] == 0.008
    volume = method.volume
    for i, frame in enumerate(metrics["frames"]):
        assert frame["voxels"] == volume.num_voxels > 100_000
        assert frame["model_bytes"] > volume.nbytes and frame["mesh_vertices"] > 1000 and frame["nodes"] > 50
        if i:
            assert STAGES <= frame["seconds"].keys()
            assert frame["gauss_newton_iterations"] >= 1
    assert sorted(p.name for p in (out / "live").iterdir()) == [f"frame-{i:06d}.ply" for i in (0, 4, 7)]
    table, faces = read_ply(out / "live" / "frame-000007.ply")
    assert table.dtype.names == VERTEX_FIELDS and all(table.dtype[n] == np.dtype("<f4") for n in VERTEX_FIELDS)
    assert len(faces) > len(table) and faces.min() == 0 and faces.max() == len(table) - 1
    assert len(table) == metrics["frames"][-1]["mesh_vertices"]
    model, model_faces = read_ply(out / "model.ply")
    assert len(model) == len(table) and np.array_equal(model_faces, faces)
    assert np.array_equal(model["x"], table["ref_x"])

    result = evaluate(out, sheet)
    for row in result["frames"]:
        assert row["accuracy_median_mm"] < 1.5, row
        assert row["completeness_10mm_pct"] > 95, row
        assert row["normal_consistency"] > 0.99, row
    assert result["frames"][0]["epe_mean_mm"] is None     # frame 0 is its own reference
    assert result["frames"][-1]["epe_mean_mm"] < 12     # 4 mm measured; the sheet moved 31 mm on average
    # The live mesh follows the moving sheet: the canonical mesh itself is far from frame 7's surface.
    gt = synth.load_groundtruth(sheet)
    truth = TriangleMesh(gt.vertices[7], gt.faces)
    ref = np.stack([table["ref_x"], table["ref_y"], table["ref_z"]], -1).astype(np.float64)
    assert np.median(truth.query(ref).distance) > 0.005
    # The fused voxels near the sheet became confident; empty space far from it stayed unobserved.
    assert metrics["frames"][-1]["observed_voxels"] > metrics["frames"][0]["observed_voxels"]


def test_orbit_fuses_a_static_scene_seen_by_a_moving_camera(tmp_path):
    seq = synth.generate("orbit", tmp_path / "orbit", frames=8, size=(320, 240))
    method, metrics = run_df(seq, tmp_path / "df", save_every=7)
    result = evaluate(tmp_path / "df", seq)
    last = result["frames"][-1]
    assert last["accuracy_median_mm"] < 1.0 and last["epe_mean_mm"] < 3.0, last
    assert result["trajectory"]["ate_cm"] < 1.0 and result["trajectory"]["rotation_error_deg"] < 0.5
    # New geometry came into view: the warp field was extended (Sec. 3.4) ...
    frames = metrics["frames"]
    assert frames[-1]["nodes"] > frames[0]["nodes"] and sum(f.get("new_nodes", 0) for f in frames) > 0
    assert frames[-1]["mesh_vertices"] > frames[0]["mesh_vertices"]
    # ... and the voxel k-NN field, updated only where new nodes won, equals one computed afresh.
    centres = method.volume.voxel_centres()
    k = method.params.warp_field.k_skin
    knn, weights = skin(centres, method.field.nodes, k, method.field.sigma_m)
    same = np.all(np.sort(knn, 1) == np.sort(method.voxel_knn, 1), axis=1)
    assert same.mean() > 0.9999     # ties between equidistant nodes may order differently
    np.testing.assert_allclose(method.voxel_weights[same], weights[same], atol=1e-5)
    fresh = node_distance_weight(centres, method.field.nodes, knn, method.params.warp_field.node_radius_m)
    np.testing.assert_allclose(method.voxel_fusion_weight[same], fresh[same], atol=1e-5)


def test_hierarchy_links_each_level_to_its_nearest_coarser_nodes():
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.25, 0.25, (4000, 3)) * [1, 1, 0.2]
    nodes = WarpField.from_points(points).nodes
    eps, beta, k = 0.025, 2.0, 3
    tree = build_hierarchy(nodes, eps, levels=4, beta=beta, k=k)
    assert len(tree.levels) == 4 and np.array_equal(tree.levels[0], np.arange(len(nodes)))
    assert np.array_equal(tree.nodes[:len(nodes)], nodes)
    sizes = [len(level) for level in tree.levels]
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] >= 1
    # Edges as (fine, coarse) pairs, read back from the graph rows (stored at the coarse end).
    j = np.repeat(np.arange(len(tree.nodes)), tree.graph.shape[1])
    i = tree.graph.reshape(-1)
    real = i != j
    edges = set(zip(i[real].tolist(), j[real].tolist()))
    for level in range(1, 4):
        coarse = tree.nodes[tree.levels[level]]
        gaps = np.linalg.norm(coarse[:, None] - coarse[None], axis=-1) + np.eye(len(coarse))
        assert gaps.min() >= eps * beta ** level * (1 - 1e-6)
        fine = tree.levels[level - 1]
        _, nearest = KDTree(coarse).query(tree.nodes[fine], k=min(k, len(coarse)))
        expected = {(int(f), int(tree.levels[level][c])) for f, row in zip(fine, nearest.reshape(len(fine), -1))
                    for c in row}
        assert expected <= edges
    assert len(edges) == sum(sizes[l] * min(k, sizes[l + 1]) for l in range(3))   # no sibling edges


def test_hierarchy_field_starts_at_the_current_warp():
    rng = np.random.default_rng(4)
    nodes = WarpField.from_points(rng.uniform(-0.2, 0.2, (3000, 3)) * [1, 1, 0.3]).nodes
    field = WarpField.identity(nodes)
    # A smooth bend: rotation about y growing with x.
    from surfelwarp.se3 import se3_exp
    xi = np.zeros((len(nodes), 6))
    xi[:, 1] = 2.0 * nodes[:, 0]
    xi[:, 5] = 0.1 * nodes[:, 0] ** 2
    field = field.with_transforms(se3_exp(xi))
    tree = build_hierarchy(nodes, 0.025, 4, 4.0, 4)
    full = with_hierarchy(field, tree)
    assert np.array_equal(full.transforms[:len(nodes)], field.transforms)
    extra = tree.nodes[len(nodes):]
    # Each regularisation node moves its own position where the warp field moves it.
    moved = full.live_nodes()[len(nodes):]
    knn, w = skin(extra, nodes, 4, field.sigma_m)
    expected, _ = warp(extra.astype(np.float64), None, knn, w, field)
    np.testing.assert_allclose(moved, expected, atol=1e-9)
    np.testing.assert_allclose(warp_transforms_at(field, nodes[:5])[:, :3, 3] + nodes[:5],
                               warp(nodes[:5].astype(np.float64), None, *skin(nodes[:5], nodes, 4, field.sigma_m),
                                    field)[0], atol=1e-9)


def test_hierarchical_regulariser_tracks_the_sheet(sheet, tmp_path):
    params = replace(FAST, hierarchical_graph=True)
    method, metrics = run_df(sheet, tmp_path / "dfh", params, frames=5, save_every=4)
    assert method.tree is not None and method.tree.num_warp_nodes == method.field.num_nodes
    assert len(method.tree.levels) >= 3
    result = evaluate(tmp_path / "dfh", sheet)
    for row in result["frames"]:
        assert row["accuracy_median_mm"] < 1.5 and row["completeness_10mm_pct"] > 95, row
