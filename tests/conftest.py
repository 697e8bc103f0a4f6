from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest

# ../shared/data beside the repository (tests that need it skip when it is absent)
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def gl():
    """A headless GL context, or the test is skipped (no EGL/Mesa on this machine)."""
    from surfelwarp.errors import GLUnavailableError
    from surfelwarp.render.context import gl_context
    try:
        return gl_context()
    except GLUnavailableError as exc:
        pytest.skip(str(exc))


@contextmanager
def numba_threads(n: int):
    """Inside the block numba's parallel loops run on n threads (at most as many as it has)."""
    import numba
    before = numba.get_num_threads()
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        numba.set_num_threads(before)


def shared_data(name: str) -> Path:
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


def sphere_depth_mm(frame: int, size=(64, 48), f=60.0) -> np.ndarray:
    """A sphere in front of a wall at 1.5 m, moving right one pixel a frame: analytic depth in mm."""
    w, h = size
    u, v = np.meshgrid(np.arange(w) - w / 2, np.arange(h) - h / 2)
    rays = np.stack([u / f, v / f, np.ones_like(u, dtype=float)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    centre = np.array([0.02 * frame, 0.0, 1.0])
    b = rays @ centre
    disc = b * b - (centre @ centre - 0.2 ** 2)
    t = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
    z = np.minimum(t * rays[..., 2], 1.5)
    return np.round(z * 1000).astype(np.uint16)


LAYOUT_FILES = {
    "volumedeform": ("frame-{:06d}.depth.png", "depthIntrinsics.txt"),
    "7scenes": ("frame-{:06d}.depth.png", "camera-intrinsics.txt"),
    "deepdeform": ("depth/{:06d}.png", "intrinsics.txt"),
    "killingfusion": ("depth_{:06d}.png", "intrinsics_kinect1.txt"),
}


COLOR_FILES = {"volumedeform": "frame-{:06d}.color.png", "7scenes": "frame-{:06d}.color.jpg",
               "deepdeform": "color/{:06d}.jpg", "killingfusion": "color_{:06d}.png"}

SPHERE_RGB, WALL_RGB = (200, 40, 40), (40, 90, 200)


def two_colours(frame: int, size=(64, 48)) -> np.ndarray:
    """(H, W, 3) uint8 RGB registered to sphere_depth_mm: the sphere SPHERE_RGB, the wall WALL_RGB."""
    sphere = sphere_depth_mm(frame, size) < 1450
    return np.where(sphere[..., None], np.uint8(SPHERE_RGB), np.uint8(WALL_RGB)).astype(np.uint8)


def write_sequence(root: Path, layout: str = "volumedeform", frames=range(3), size=(64, 48),
                   four_by_four: bool = False, color=None) -> Path:
    """color: frame index -> (h, w, 3) uint8 RGB image (any size), written as the layout's colour
    file (BGR on disk, as cv2 and the datasets store it); None: no colour files."""
    depth_name, intrinsics_name = LAYOUT_FILES[layout]
    root.mkdir(parents=True, exist_ok=True)
    for i in frames:
        path = root / depth_name.format(i)
        path.parent.mkdir(exist_ok=True)
        cv2.imwrite(str(path), sphere_depth_mm(i, size))
        if color is not None:
            path = root / COLOR_FILES[layout].format(i)
            path.parent.mkdir(exist_ok=True)
            quality = [cv2.IMWRITE_JPEG_QUALITY, 100] if path.suffix == ".jpg" else []
            cv2.imwrite(str(path), np.ascontiguousarray(color(i)[..., ::-1]), quality)
    K = np.array([[60.0, 0, size[0] / 2], [0, 60.0, size[1] / 2], [0, 0, 1]])
    if four_by_four:
        K4 = np.eye(4)
        K4[:3, :3] = K
        K = K4
    np.savetxt(root / intrinsics_name, K)
    return root


@pytest.fixture
def sequence(tmp_path) -> Path:
    return write_sequence(tmp_path / "seq")
