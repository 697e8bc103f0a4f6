"""What a run shows (issue 21): normal-map renders against analytic normals, the per-frame
pictures and their video, the model's mesh against the true surface, the PLYs read by other
readers (plyfile; Open3D where installed), `surfelwarp mesh` and `surfelwarp view`."""
import json

import cv2
import numpy as np
import pytest
from plyfile import PlyData

from surfelwarp.data_tools import synth
from surfelwarp.data_tools.evaluate import load_groundtruth
from surfelwarp.data_tools.geometry import TriangleMesh
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.surfel_mesh import mesh_surfels
from surfelwarp.io.ply import read_ply, vertex_table
from surfelwarp.render.views import depth_colours, frame_panel, live_view

from conftest import write_sequence
from test_faults import run_here

INTR = Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)


def decoded_normals(rgb: np.ndarray) -> np.ndarray:
    """The camera-frame normals a normal-map colour stands for (views.normal_colours inverted)."""
    n = (2.0 * rgb - 1.0) * np.array([1.0, -1.0, -1.0])
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def pixel_rays(intr: Intrinsics) -> np.ndarray:
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], -1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def surfel_table(points, normals, radius):
    n = len(points)
    return vertex_table(points.astype(np.float32), normals.astype(np.float32), points.astype(np.float32),
                        np.full(n, radius, np.float32), np.ones(n, np.float32), np.arange(n, dtype=np.uint32))


def test_normal_map_of_a_sphere_and_a_plane_is_analytic(gl):
    # sphere: radius 0.1 at z = 0.6; tilted plane behind it; surfels ~1.8 mm apart with disks of
    # 2.5 mm (a pixel shows the front disk, tangent a little off: ~1 degree on this sphere)
    k = np.arange(40000) + 0.5
    phi, theta = np.arccos(1 - 2 * k / len(k)), np.pi * (1 + 5 ** 0.5) * k
    out = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    sphere = np.array([0.0, 0.0, 0.6]) + 0.1 * out
    plane_n = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    xs, ys = np.meshgrid(np.linspace(-0.6, 0.6, 400), np.linspace(-0.45, 0.45, 300))
    plane = np.stack([xs.ravel(), ys.ravel(), 1.2 + (0.3 * xs.ravel() - 0.2 * ys.ravel())], 1)
    table = surfel_table(np.concatenate([sphere, plane]), np.concatenate([out, np.tile(plane_n, (len(plane), 1))]),
                         0.0025)
    normals = decoded_normals(live_view(table, None, INTR))
    rays = pixel_rays(INTR)
    # where each pixel's ray meets the sphere
    b = rays @ np.array([0.0, 0.0, 0.6])
    disc = b ** 2 - (0.36 - 0.01)
    hit = disc > 0
    t = b - np.sqrt(np.maximum(disc, 0))
    sphere_n = (rays * t[..., None] - [0, 0, 0.6]) / 0.1
    inner = hit & (np.sum(sphere_n * -rays, -1) > 0.3)        # away from the grazing rim
    assert inner.sum() > 1000
    assert np.median(angle_deg(normals[inner], sphere_n[inner])) < 2.0
    behind = ~hit
    behind[:8], behind[-8:], behind[:, :8], behind[:, -8:] = False, False, False, False
    assert np.percentile(angle_deg(normals[behind], plane_n), 95) < 1.0


def test_panel_keeps_depth_and_colour_beside_the_render():
    depth = np.zeros((4, 6), np.float32)
    depth[:, 3:] = np.linspace(1.0, 2.0, 3)
    coloured = depth_colours(depth)
    assert (coloured[:, :3] == 0).all() and (coloured[:, 3:] > 0).any(-1).all()
    assert coloured[0, 3, 0] > coloured[0, 5, 0] and coloured[0, 5, 2] > coloured[0, 3, 2]  # near red, far blue
    colour = np.full((4, 6, 3), 7, np.uint8)
    panel = frame_panel(np.ones((4, 6, 3)), depth, colour)
    assert panel.shape == (4, 18, 3) and (panel[:, :6] == 255).all() and (panel[:, 12:] == 7).all()
    assert frame_panel(np.ones((4, 6, 3)), depth, None).shape == (4, 12, 3)


@pytest.fixture(scope="module")
def touch(tmp_path_factory):
    root = tmp_path_factory.mktemp("touch")
    seq = synth.generate("touch", root / "seq", frames=12, size=(320, 240))
    out = root / "out"
    assert run_here("run", seq, "--out", out, "--save-every", 4)[0] == 0
    return seq, out


def test_pictures_and_video_of_every_saved_frame(touch, tmp_path):
    seq, out = touch
    saved = sorted(int(p.stem[6:]) for p in (out / "live").glob("frame-*.ply"))
    assert saved == [0, 4, 8, 11]
    assert sorted(int(p.stem[6:]) for p in (out / "render").glob("frame-*.png")) == saved
    picture = cv2.imread(str(out / "render" / "frame-000008.png"))
    assert picture.shape == (240, 960, 3)                        # normal map | depth | colour
    colour = cv2.imread(str(seq / "frame-000008.color.png"))
    assert np.array_equal(picture[:, 640:], colour)
    video = cv2.VideoCapture(str(out / "live.mp4"))
    count = 0
    while True:
        ok, frame = video.read()
        if not ok:
            break
        assert frame.shape == picture.shape
        count += 1
    assert count == len(saved)
    frames = json.loads((out / "metrics.json").read_text())["frames"]
    assert [f["frame"] for f in frames if "render" in f["seconds"]] == saved
    assert run_here("run", seq, "--out", tmp_path / "plain", "--save-every", 4, "--max-frames", 3, "--no-render")[0] == 0
    assert not (tmp_path / "plain" / "render").exists() and not (tmp_path / "plain" / "live.mp4").exists()


def test_model_mesh_lies_on_the_true_surface_and_covers_the_surfels(touch):
    seq, out = touch
    mesh, faces = read_ply(out / "model_mesh.ply")
    assert mesh.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue") and len(faces) > 1000
    reference = json.loads((out / "metrics.json").read_text())["frames"][-1]["reference_frame"]
    gt = load_groundtruth(seq)
    truth = TriangleMesh(gt.vertices[gt.index(reference)].astype(np.float64), gt.faces)
    vertices = np.stack([mesh[k] for k in "xyz"], 1).astype(np.float64)
    assert np.median(truth.query(vertices).distance) < 1e-3
    surfels, _ = read_ply(out / "model.ply")
    points = np.stack([surfels[k] for k in "xyz"], 1).astype(np.float64)
    assert np.mean(TriangleMesh(vertices, faces).query(points).distance < 1e-3) > 0.95


def test_no_faces_between_fingers_two_centimetres_apart():
    # two finger-like cylinders (radius 8 mm) 2.1 cm apart, surfels 1 mm apart
    t, y = np.meshgrid(np.linspace(0, 2 * np.pi, 50, endpoint=False), np.linspace(-0.04, 0.04, 80))
    ring = np.stack([np.cos(t.ravel()), np.zeros(t.size), np.sin(t.ravel())], 1)
    fingers = [np.array([x, 0.0, 0.5]) + 0.008 * ring + np.stack([0 * y.ravel(), y.ravel(), 0 * y.ravel()], 1)
               for x in (-0.0185, 0.0185)]
    mesh = mesh_surfels(np.concatenate(fingers), np.concatenate([ring, ring]), voxel_m=0.0015)
    x = mesh.vertices[mesh.faces][..., 0]
    assert len(mesh.faces) > 2000 and not np.any((x.min(1) < -0.005) & (x.max(1) > 0.005))


def test_other_readers_open_the_outputs(touch):
    _, out = touch
    ply = PlyData.read(str(out / "model_mesh.ply"))
    assert {"x", "nx", "red"} <= {p.name for p in ply["vertex"].properties}
    assert len(ply["face"]["vertex_indices"]) == len(read_ply(out / "model_mesh.ply")[1])
    live = PlyData.read(str(out / "live" / "frame-000008.ply"))["vertex"]
    assert {"x", "nx", "ref_x", "radius", "confidence", "id", "red"} <= {p.name for p in live.properties}
    o3d = pytest.importorskip("open3d")
    mesh = o3d.io.read_triangle_mesh(str(out / "model_mesh.ply"))
    assert mesh.has_vertex_normals() and mesh.has_vertex_colors() and len(mesh.triangles) > 1000
    cloud = o3d.io.read_point_cloud(str(out / "live" / "frame-000008.ply"))
    assert cloud.has_normals() and cloud.has_colors() and len(cloud.points) == live.count


def test_mesh_and_view_commands(touch, tmp_path):
    _, out = touch
    code, err = run_here("mesh", out, "--frame", 4)
    assert code == 0, err
    mesh, faces = read_ply(out / "mesh" / "frame-000004.ply")
    assert len(faces) > 1000 and np.isfinite(mesh["x"]).all()
    code, err = run_here("mesh", out, "--frame", 5)
    assert code == 2 and "frame-000005.ply: no such file (saved frames: 0, 4, 8, 11)" in err
    code, err = run_here("view", out, "--html", tmp_path / "page.html")
    assert code == 0 and (tmp_path / "page.html").stat().st_size > 10_000


def test_dynamicfusion_renders_and_meshes_its_own_surface(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(3))
    config = tmp_path / "coarse.json"
    config.write_text('{"tsdf": {"voxel_size_m": 0.02, "truncation_m": 0.06}}')
    out = tmp_path / "out"
    assert run_here("run", seq, "--out", out, "--method", "dynamicfusion", "--config", config)[0] == 0
    model, model_faces = read_ply(out / "model.ply")
    mesh, faces = read_ply(out / "model_mesh.ply")
    assert np.array_equal(faces, model_faces) and np.array_equal(mesh["x"], model["x"])
    picture = cv2.imread(str(out / "render" / "frame-000002.png"))
    assert picture.shape == (48, 128, 3) and (picture[:, :64] != 255).any()   # the mesh drawn
