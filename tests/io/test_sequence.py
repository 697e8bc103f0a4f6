import cv2
import numpy as np
import pytest

from surfelwarp.errors import InputError
from surfelwarp.io.sequence import open_sequence, parse_intrinsics_flag

from conftest import shared_data, write_sequence


@pytest.mark.parametrize("layout", ["volumedeform", "7scenes", "deepdeform", "killingfusion"])
def test_every_layout_is_detected(tmp_path, layout):
    seq = open_sequence(write_sequence(tmp_path / layout, layout, frames=[0, 1, 5], four_by_four=layout == "deepdeform"))
    assert seq.layout == layout
    assert [f.index for f in seq.files] == [0, 1, 5]
    assert (seq.intrinsics.fx, seq.intrinsics.cx, seq.intrinsics.width, seq.intrinsics.height) == (60, 32, 64, 48)
    frame, depth = next(seq.frames())
    assert depth.dtype == np.float32 and depth.shape == (48, 64)
    assert depth.max() == pytest.approx(1.5) and depth.min() == pytest.approx(0.8, abs=0.01)


def test_start_max_frames_and_depth_scale(tmp_path):
    root = write_sequence(tmp_path / "s", frames=range(6))
    seq = open_sequence(root, start=2, max_frames=3, depth_scale=5000)
    assert [f.index for f in seq.files] == [2, 3, 4]
    assert next(seq.frames())[1].max() == pytest.approx(1.5 / 5)


def test_intrinsics_flag_overrides_and_supplies(tmp_path):
    root = write_sequence(tmp_path / "s")
    (root / "depthIntrinsics.txt").unlink()
    with pytest.raises(InputError, match="no intrinsics file"):
        open_sequence(root)
    seq = open_sequence(root, intrinsics=parse_intrinsics_flag("100,101,30,20"))
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (100, 101, 30, 20)
    with pytest.raises(InputError, match="four numbers"):
        parse_intrinsics_flag("1,2,3")


def test_frames_are_read_lazily(tmp_path, monkeypatch):
    root = write_sequence(tmp_path / "s", frames=range(5))
    seq = open_sequence(root)
    decoded = []
    real_imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda p, *a: decoded.append(p) or real_imread(p, *a))
    frames = seq.frames()
    next(frames)
    assert len(decoded) == 1


@pytest.mark.parametrize("name,layout,n", [("rigid-7scenes", "7scenes", 200), ("snoopy-pair", "killingfusion", 2),
                                           ("deepdeform-shirt-pair", "deepdeform", 2)])
def test_shared_data_loads(name, layout, n):
    seq = open_sequence(shared_data(name))
    assert seq.layout == layout and len(seq) == n
    assert (seq.intrinsics.width, seq.intrinsics.height) == (640, 480)
    if layout == "7scenes":
        assert seq.read_pose(seq.files[0]).shape == (4, 4)
    if layout == "deepdeform":
        assert [f.index for f in seq.files] == [0, 110]
