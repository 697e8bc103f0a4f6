"""Colour frames: read as RGB where the layout registers them to depth, resized when only their
size differs, otherwise not used; every decision said once."""
import cv2
import numpy as np
import pytest

from surfelwarp.errors import InputError
from surfelwarp.io.ply import read_ply
from surfelwarp.io.sequence import open_sequence
from surfelwarp.methods.observe import ObserveMethod
from surfelwarp.run import run_sequence

from conftest import COLOR_FILES, shared_data, write_sequence


def pattern(frame: int, size=(64, 48)) -> np.ndarray:
    """RGB with a different ramp in each channel: red along columns, blue along rows, green by frame."""
    w, h = size
    rgb = np.empty((h, w, 3), np.uint8)
    rgb[..., 0] = (3 + 3 * np.arange(w))[None, :]
    rgb[..., 1] = 60 + 40 * frame
    rgb[..., 2] = (250 - 5 * np.arange(h))[:, None]
    return rgb


def run_observe(seq_dir, out, capsys):
    run_sequence(open_sequence(seq_dir), out, ObserveMethod(), progress=False)
    return capsys.readouterr().err


@pytest.mark.parametrize("layout", ["volumedeform", "deepdeform"])
def test_registered_colour_is_read_as_rgb(tmp_path, layout):
    seq = open_sequence(write_sequence(tmp_path / layout, layout, frames=range(3), color=pattern,
                                       four_by_four=layout == "deepdeform"))
    assert seq.has_color and seq.notes == ()
    for files in seq.files:
        rgb = seq.read_color(files)
        assert rgb.dtype == np.uint8 and rgb.shape == (48, 64, 3)
        diff = np.abs(rgb.astype(int) - pattern(files.index))
        if layout == "volumedeform":      # PNG: lossless
            assert diff.max() == 0
        else:                              # JPEG at quality 100: close, and far from the BGR order
            assert diff.mean() < 2 and np.abs(rgb.astype(int) - pattern(files.index)[..., ::-1]).mean() > 50


@pytest.mark.parametrize("layout", ["7scenes", "killingfusion"])
def test_unregistered_colour_is_not_used_and_said_once(tmp_path, layout, capsys):
    root = write_sequence(tmp_path / layout, layout, frames=range(3), color=pattern)
    seq = open_sequence(root)
    assert all(f.color is not None for f in seq.files)
    assert not seq.has_color and all(seq.read_color(f) is None for f in seq.files)
    assert len(seq.notes) == 1 and "not registered" in seq.notes[0]
    err = run_observe(root, tmp_path / "out", capsys)
    assert err.count("not registered") == 1 and err.count("\n") == 1, err
    assert "red" not in read_ply(tmp_path / "out" / "model.ply")[0].dtype.names


def test_colour_of_the_depth_aspect_ratio_is_resized(tmp_path, capsys):
    # Each depth-sized pixel is a 2x2 block of the large image, +-2 in a checker: the block's
    # mean (INTER_AREA) is the pixel, any single sample of it is 2 off.
    def big(i):
        block = np.repeat(np.repeat(pattern(i).astype(int), 2, axis=0), 2, axis=1)
        checker = 2 * np.where((np.arange(96)[:, None] + np.arange(128)[None, :]) % 2 == 0, 1, -1)
        return (block + checker[..., None]).astype(np.uint8)
    root = write_sequence(tmp_path / "s", frames=range(2), color=big)
    seq = open_sequence(root)
    assert seq.has_color and seq.color_size == (128, 96)
    assert len(seq.notes) == 1 and "128x96" in seq.notes[0] and "resized" in seq.notes[0]
    assert np.array_equal(seq.read_color(seq.files[1]), pattern(1))
    assert run_observe(root, tmp_path / "out", capsys).count("resized") == 1


def test_colour_of_another_aspect_ratio_is_not_used(tmp_path, capsys):
    root = write_sequence(tmp_path / "s", frames=range(2), color=lambda i: np.zeros((64, 64, 3), np.uint8))
    seq = open_sequence(root)
    assert not seq.has_color and seq.read_color(seq.files[0]) is None
    assert len(seq.notes) == 1 and "another aspect ratio" in seq.notes[0] and "64x64" in seq.notes[0]
    assert run_observe(root, tmp_path / "out", capsys).count("aspect ratio") == 1


def test_colour_frames_of_other_sizes_are_used_where_they_map(tmp_path, capsys):
    """CONTRACT.md: a colour frame of another size than the depth is used where it maps (the
    depth's aspect ratio: resized), its frame runs without colour where it does not; said once."""
    root = write_sequence(tmp_path / "s", frames=range(4), color=pattern)
    half = cv2.resize(pattern(1), (32, 24), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(root / "frame-000001.color.png"), half[..., ::-1])
    cv2.imwrite(str(root / "frame-000002.color.png"), np.zeros((24, 24, 3), np.uint8))
    seq = open_sequence(root)
    assert seq.has_color and seq.color_size == (64, 48) and len(seq.notes) == 2
    assert "32x24" in seq.notes[0] and "resized" in seq.notes[0]
    assert "1 colour frame(s)" in seq.notes[1] and "frame-000002.color.png" in seq.notes[1]
    colours = [seq.read_color(f) for f in seq.files]
    assert [c is None for c in colours] == [False, False, True, False]
    assert colours[1].shape == (48, 64, 3) and np.abs(colours[1].astype(int) - pattern(1)).mean() < 40
    err = run_observe(root, tmp_path / "out", capsys)
    assert err.count("resized") == 1 and err.count("aspect ratio") == 1, err


def test_frames_without_colour_run_without_it(tmp_path, capsys):
    root = write_sequence(tmp_path / "s", frames=range(5), color=pattern)
    for i in (2, 4):
        (root / COLOR_FILES["volumedeform"].format(i)).unlink()
    seq = open_sequence(root)
    assert seq.has_color and len(seq.notes) == 1
    assert "2 of 5 frames" in seq.notes[0] and "frame-000002.color.png" in seq.notes[0]
    assert [seq.read_color(f) is None for f in seq.files] == [False, False, True, False, True]
    err = run_observe(root, tmp_path / "out", capsys)
    assert err.count("2 of 5 frames") == 1 and err.count("\n") == 1, err
    # observe writes each frame's pixel colours; a frame without them keeps the layout, 0 0 0.
    table, _ = read_ply(tmp_path / "out" / "live" / "frame-000004.ply")
    assert table.dtype.names[-3:] == ("red", "green", "blue") and not table["red"].any()
    assert read_ply(tmp_path / "out" / "live" / "frame-000000.ply")[0]["blue"].min() > 0


def test_alpha_is_dropped(tmp_path):
    def rgba(i):
        out = np.empty((48, 64, 4), np.uint8)
        out[..., :3], out[..., 3] = pattern(i), 77
        return out
    # write_sequence reverses the channels: A R G B reversed is the B G R A that cv2 writes as RGBA.
    root = write_sequence(tmp_path / "s", frames=range(2), color=lambda i: rgba(i)[..., [3, 0, 1, 2]])
    seq = open_sequence(root)
    assert seq.has_color and np.array_equal(seq.read_color(seq.files[1]), pattern(1))


@pytest.mark.parametrize("bad", ["16bit", "grey", "not_png", "empty"])
def test_bad_colour_frames_are_named_when_opening(tmp_path, bad):
    root = write_sequence(tmp_path / "s", frames=range(3), color=pattern)
    path = root / "frame-000001.color.png"
    if bad == "16bit":
        cv2.imwrite(str(path), np.zeros((48, 64, 3), np.uint16))
    elif bad == "grey":
        cv2.imwrite(str(path), np.zeros((48, 64), np.uint8))
    elif bad == "not_png":
        path.write_text("hello")
    else:       # a header that says 64x0 (no decoder is asked)
        data = bytearray(path.read_bytes())
        data[20:24] = (0).to_bytes(4, "big")
        path.write_bytes(bytes(data))
    with pytest.raises(InputError) as err:
        open_sequence(root)
    expected = {"16bit": "8-bit RGB or RGBA, found 16-bit RGB", "grey": "found 8-bit grayscale",
                "not_png": "not a PNG", "empty": "64x0: empty"}[bad]
    assert err.value.path == path and expected in err.value.problem


def test_bad_colour_jpeg_is_named_when_opening(tmp_path):
    root = write_sequence(tmp_path / "s", "deepdeform", frames=range(2), color=pattern)
    grey = root / "color" / "000001.jpg"
    cv2.imwrite(str(grey), np.full((48, 64), 128, np.uint8))
    with pytest.raises(InputError, match="3 channels, found mode L") as err:
        open_sequence(root)
    assert err.value.path == grey
    grey.write_bytes(b"\xff\xd8 not really a jpeg")
    with pytest.raises(InputError, match="cannot read colour frame"):
        open_sequence(root)


def test_damaged_colour_pixels_are_an_input_error_when_read(tmp_path):
    root = write_sequence(tmp_path / "s", frames=range(2), color=pattern)
    path = root / "frame-000001.color.png"
    data = path.read_bytes()
    path.write_bytes(data[:40] + b"\0" * (len(data) - 40))     # header intact
    seq = open_sequence(root)
    assert seq.read_color(seq.files[0]) is not None
    with pytest.raises(InputError, match="cannot decode colour frame") as err:
        seq.read_color(seq.files[1])
    assert err.value.path == path


def test_colour_is_read_lazily(tmp_path, monkeypatch):
    root = write_sequence(tmp_path / "s", frames=range(4), color=pattern)
    decoded = []
    real_imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda p, *a: decoded.append(p) or real_imread(p, *a))
    seq = open_sequence(root)
    assert decoded == []
    seq.read_color(seq.files[2])
    assert decoded == [str(root / "frame-000002.color.png")]


def test_shared_deepdeform_colour_is_registered_rgb():
    root = shared_data("deepdeform-shirt-pair")
    seq = open_sequence(root)
    # a pair 110 frames apart: the gap is named, nothing about colour
    assert seq.has_color and seq.notes == ("109 frame number(s) missing, the run goes on without them: 1-109",)
    rgb = seq.read_color(seq.files[1])
    assert np.array_equal(rgb, cv2.imread(str(root / "color" / "000110.jpg"))[..., ::-1])
