"""The HTML viewer of a run's live frames: the points it embeds, the point limit, bad folders,
nothing fetched from the network, and (where a Chromium is installed) that it draws."""
import base64
import json
import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest

from surfelwarp.errors import InputError
from surfelwarp.io.ply import vertex_table, write_ply
from surfelwarp.report.viewer import write_viewer

FLIP = np.array([1.0, -1.0, -1.0], np.float32)
RED = (230, 40, 40)


def red(count):
    return np.tile(np.float32(RED), (count, 1))


def write_run(out, frames, method="surfelwarp"):
    """A run folder: frames maps frame number -> (positions, rgb or None); normals face the camera."""
    for frame, (position, rgb) in frames.items():
        position = np.asarray(position, np.float32)
        normal = np.tile(np.float32([0.0, 0.0, -1.0]), (len(position), 1))
        write_ply(out / "live" / f"frame-{frame:06d}.ply", vertex_table(
            position, normal, position, np.full(len(position), 0.01, np.float32),
            np.ones(len(position), np.float32), np.arange(len(position), dtype=np.uint32), rgb))
    eye = np.eye(4).tolist()
    (out / "metrics.json").write_text(json.dumps({"method": method, "frames": [
        {"frame": frame, "camera_to_world": eye} for frame in frames]}))
    return out


def grid(count, z=1.0, width=0.4):
    """count points on a square grid of side `width` at depth z, x increasing with the index."""
    side = int(np.ceil(np.sqrt(count)))
    i = np.arange(count)
    return np.stack([(i % side) / side * width - width / 2, (i // side) / side * width - width / 2,
                     np.full(count, z)], -1).astype(np.float32)


def embedded(page: str) -> dict:
    """The page's data block, with each frame's positions and colours decoded to arrays."""
    data = json.loads(re.search(r'<script id="frames" type="application/json">(.*?)</script>', page, re.S)[1])
    for f in data["frames"]:
        f["positions"] = np.frombuffer(base64.b64decode(f["positions"]), "<f4").reshape(-1, 3)
        f["colours"] = np.frombuffer(base64.b64decode(f["colours"]), np.uint8).reshape(-1, 3)
    return data


def test_points_and_colours_come_back_exactly_in_the_y_up_frame(tmp_path):
    rng = np.random.default_rng(3)
    position = rng.uniform([-0.3, -0.2, 0.8], [0.3, 0.2, 1.4], (7, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (7, 3)).astype(np.float32)
    out = write_run(tmp_path / "out", {4: (position, rgb), 9: (grid(5), None)})
    path = write_viewer(out)
    assert path == out / "view.html"
    page = path.read_text()
    data = embedded(page)
    assert [f["frame"] for f in data["frames"]] == [4, 9]
    first = data["frames"][0]
    np.testing.assert_array_equal(first["positions"], position * FLIP)
    np.testing.assert_array_equal(first["colours"], rgb.astype(np.uint8))
    assert first["shown"] == 7
    assert "showing 12 of 12 points" in page
    centre = (np.minimum(position.min(0), grid(5).min(0)) + np.maximum(position.max(0), grid(5).max(0))) / 2
    np.testing.assert_allclose(data["centre"], centre * FLIP, atol=1e-6)


def test_without_colour_points_take_the_normal_map_colour(tmp_path):
    out = write_run(tmp_path / "out", {0: (grid(4), None)})
    data = embedded(write_viewer(out).read_text())
    # A normal facing the camera, (0, 0, -1), is +z in the page's y-up frame: light blue.
    np.testing.assert_array_equal(data["frames"][0]["colours"], np.tile(np.uint8([128, 128, 255]), (4, 1)))


def test_subsampling_keeps_the_limit_and_is_deterministic(tmp_path):
    counts = {0: 1000, 5: 2000, 10: 3000}
    out = write_run(tmp_path / "out", {frame: (grid(n), None) for frame, n in counts.items()})
    first = write_viewer(out, tmp_path / "a.html", max_points=1000)
    second = write_viewer(out, tmp_path / "b.html", max_points=1000)
    assert first.read_bytes() == second.read_bytes()
    page = first.read_text()
    data = embedded(page)
    shown = [f["shown"] for f in data["frames"]]
    assert sum(shown) <= 1000 and shown == [166, 333, 500]        # the same share of each frame
    assert f"showing {sum(shown):,} of 6,000 points" in page
    for f, n in zip(data["frames"], counts.values()):
        assert len(f["positions"]) == f["shown"] == len(f["colours"])
        row = {tuple(p): i for i, p in enumerate(grid(n) * FLIP)}
        rows = [row[tuple(p)] for p in f["positions"]]          # every shown point is one of the file's,
        assert rows == sorted(set(rows)) and rows[-1] > 0.9 * n   # once, in file order, over the whole frame


def test_a_mesh_shows_its_vertices(tmp_path):
    out = tmp_path / "out"
    position = grid(4)
    normal = np.tile(np.float32([0.0, 0.0, -1.0]), (4, 1))
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    write_ply(out / "live" / "frame-000002.ply", vertex_table(position, normal, position), faces)
    data = embedded(write_viewer(out).read_text())
    np.testing.assert_array_equal(data["frames"][0]["positions"], position * FLIP)


def test_a_limit_above_the_points_keeps_them_all(tmp_path):
    out = write_run(tmp_path / "out", {0: (grid(50), None), 1: (grid(60), None)})
    data = embedded(write_viewer(out, max_points=110).read_text())
    assert [f["shown"] for f in data["frames"]] == [50, 60]


@pytest.mark.parametrize("live_folder", [True, False])
def test_a_folder_without_live_frames_is_an_input_error(tmp_path, live_folder):
    out = tmp_path / "out"
    (out / "live" if live_folder else out).mkdir(parents=True)
    (out / "model.ply").write_bytes(b"")
    with pytest.raises(InputError, match="no live frames") as error:
        write_viewer(out)
    assert error.value.path == out
    assert not (out / "view.html").exists()


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_a_damaged_ply_is_an_input_error_naming_the_file(tmp_path, damage):
    out = write_run(tmp_path / "out", {0: (grid(20), None), 3: (grid(20), None)})
    broken = out / "live" / "frame-000003.ply"
    data = broken.read_bytes()
    broken.write_bytes({"truncated": data[:-50], "garbage": b"\x00\xff not a ply", "empty": b""}[damage])
    with pytest.raises(InputError) as error:
        write_viewer(out)
    assert error.value.path == broken and "frame-000003.ply" in str(error.value)
    assert "\n" not in str(error.value)
    assert not (out / "view.html").exists()


def test_the_page_loads_nothing_from_outside(tmp_path):
    page = write_viewer(write_run(tmp_path / "out", {0: (grid(10), red(10))})).read_text()
    assert "http://" not in page and "https://" not in page
    assert not re.search(r"<(script|link|img|iframe)\b[^>]*\b(src|href)\s*=", page, re.I)
    assert "@import" not in page and "url(" not in page


def test_the_method_name_is_text_not_markup(tmp_path):
    out = write_run(tmp_path / "out", {0: (grid(10), None)}, method='<b onclick="x()">&')
    page = write_viewer(out).read_text()
    assert "<b onclick" not in page and "&lt;b onclick=&quot;x()&quot;&gt;&amp;" in page


def test_the_page_script_parses(tmp_path):
    node = shutil.which("node")
    if node is None:
        pytest.skip("no node on PATH to check the script's syntax")
    page = write_viewer(write_run(tmp_path / "out", {0: (grid(10), None)})).read_text()
    scripts = re.findall(r"<script>(.*?)</script>", page, re.S)
    assert len(scripts) == 1
    (tmp_path / "viewer.js").write_text(scripts[0])
    result = subprocess.run([node, "--check", str(tmp_path / "viewer.js")], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def chromium():
    for name in ("chromium", "chromium-browser", "google-chrome", "headless_shell"):
        if shutil.which(name):
            return shutil.which(name)
    pytest.skip("no Chromium-family browser on PATH")


def test_headless_chromium_draws_the_points(tmp_path):
    browser = chromium()
    page = write_viewer(write_run(tmp_path / "out", {0: (grid(10_000), red(10_000))}))
    shot = tmp_path / "shot.png"
    # Software GL (newer Chromes also want --enable-unsafe-swiftshader for WebGL on it); a profile
    # of its own and no sandbox so it runs as root in a container.
    command = [browser, "--headless", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
               "--no-sandbox", "--no-first-run", f"--user-data-dir={tmp_path / 'profile'}", "--hide-scrollbars",
               "--virtual-time-budget=3000", f"--screenshot={shot}", "--window-size=800,600", page.as_uri()]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert shot.is_file(), f"no screenshot (exit {result.returncode}): {result.stderr[-2000:]}"
    image = cv2.imread(str(shot))[..., ::-1].astype(int)
    background = image[-5, -5]
    assert (np.abs(image - background).max(-1) > 30).any(), "the screenshot is one flat colour"
    # Not only the text panel: the points, in their colour, around the middle of the window.
    middle = image[200:400, 300:500]
    assert (np.abs(middle - np.array(RED)).max(-1) < 40).sum() > 100
