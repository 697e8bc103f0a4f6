"""Depth sequences on disk: layout detection, intrinsics, lazy frame reading.

The four layouts of CONTRACT.md are recognised by their file names. Every frame's
PNG header is checked when the sequence is opened, so a bad frame is reported
before any output is written; pixels are only decoded when a frame is read.
Colour is used only where the layout registers it to the depth image and its size maps onto
the depth's; plan_color decides that once, when the sequence is opened, and checks the colour
headers the same way.
"""
from __future__ import annotations

import os
import re
import struct
import sys
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from surfelwarp.errors import InputError
from surfelwarp.geometry.camera import Intrinsics


@dataclass(frozen=True)
class FrameFiles:
    index: int
    depth: Path
    color: Path | None = None
    pose: Path | None = None
    mask: Path | None = None


@dataclass(frozen=True)
class Layout:
    name: str
    depth_pattern: re.Pattern       # matched against paths relative to the sequence folder
    intrinsics_glob: str
    sibling: dict                   # kind -> format string of the frame index, relative path
    # The colour pixel (u, v) sees what the depth pixel (u, v) does. 7-Scenes and KillingFusion
    # ship raw colour from a camera beside the depth sensor, which would need its extrinsics.
    color_registered: bool = False


LAYOUTS = (
    Layout("volumedeform", re.compile(r"frame-(\d+)\.depth\.png"), "depthIntrinsics.txt",
           {"color": "frame-{:06d}.color.png"}, color_registered=True),
    Layout("7scenes", re.compile(r"frame-(\d+)\.depth\.png"), "camera-intrinsics.txt",
           {"color": "frame-{:06d}.color.jpg", "pose": "frame-{:06d}.pose.txt"}),
    Layout("deepdeform", re.compile(r"depth/(\d+)\.png"), "intrinsics.txt",
           {"color": "color/{:06d}.jpg"}, color_registered=True),
    Layout("killingfusion", re.compile(r"depth_(\d+)\.png"), "intrinsics*.txt",
           {"color": "color_{:06d}.png", "mask": "omask_{:06d}.png"}),
)


@contextmanager
def _quiet_stderr():
    """File descriptor 2 to /dev/null: libpng and libjpeg print their complaints about a damaged
    file there, beside the one line the run says about it."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _imread(path: Path) -> np.ndarray | None:
    """cv2.imread unchanged (no EXIF rotation, which would undo a registration), quietly."""
    with _quiet_stderr():
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def parse_intrinsics_file(path: Path) -> Intrinsics:
    """A 3x3 or 4x4 camera matrix, whitespace separated."""
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read intrinsics file ({exc.__class__.__name__})") from None
    except ValueError:
        raise InputError(path, "intrinsics file does not parse: expected a 3x3 or 4x4 matrix of numbers") from None
    if values.size not in (9, 16):
        raise InputError(path, f"intrinsics file does not parse: expected 9 or 16 numbers, found {values.size}")
    m = values.reshape(3, 3) if values.size == 9 else values.reshape(4, 4)
    fx, fy, cx, cy = m[0, 0], m[1, 1], m[0, 2], m[1, 2]
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise InputError(path, "intrinsics file does not parse: focal lengths must be positive numbers")
    return Intrinsics(float(fx), float(fy), float(cx), float(cy))


def check_principal_point(intrinsics: Intrinsics, source: str | Path | None, width: int, height: int) -> None:
    """The principal point lies in the image (every real camera's does)."""
    if not (0 <= intrinsics.cx <= width and 0 <= intrinsics.cy <= height):
        where = "--intrinsics" if source is None else None
        raise InputError(source, f"{where + ': ' if where else ''}principal point ({intrinsics.cx:g}, "
                                 f"{intrinsics.cy:g}) lies outside the {width}x{height} image")


def parse_intrinsics_flag(text: str) -> Intrinsics:
    try:
        fx, fy, cx, cy = (float(x) for x in text.split(","))
    except ValueError:
        raise InputError(None, f"--intrinsics {text!r}: expected four numbers fx,fy,cx,cy") from None
    if not np.isfinite([fx, fy, cx, cy]).all():
        raise InputError(None, f"--intrinsics {text!r}: expected finite numbers")
    if fx <= 0 or fy <= 0:
        raise InputError(None, f"--intrinsics {text!r}: focal lengths must be positive")
    return Intrinsics(fx, fy, cx, cy)


def png_header(path: Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from the IHDR chunk, without decoding pixels."""
    try:
        with open(path, "rb") as f:
            head = f.read(29)
    except OSError as exc:
        raise InputError(path, f"cannot read frame ({exc.strerror or exc.__class__.__name__})") from None
    if len(head) < 29 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise InputError(path, "not a PNG file")
    width, height, bit_depth, colour_type = struct.unpack(">IIBB", head[16:26])
    return width, height, bit_depth, colour_type


_PNG_KINDS = {0: "grayscale", 2: "RGB", 3: "palette", 4: "grayscale+alpha", 6: "RGBA"}


def _check_depth_header(path: Path, size: tuple[int, int] | None) -> tuple[int, int]:
    width, height, bit_depth, colour_type = png_header(path)
    if bit_depth != 16 or colour_type != 0:
        kind = _PNG_KINDS.get(colour_type, "unknown")
        raise InputError(path, f"depth PNG must be 16-bit single-channel, found {bit_depth}-bit {kind}")
    if size is not None and (width, height) != size:
        raise InputError(path, f"frame is {width}x{height}, but the first frame is {size[0]}x{size[1]}")
    return width, height


def color_header(path: Path) -> tuple[int, int]:
    """(width, height) of a colour frame from its header, which must say 8-bit, 3 or 4 channels
    and a size that is not empty."""
    if path.suffix.lower() == ".png":
        width, height, bit_depth, colour_type = png_header(path)
        if bit_depth != 8 or colour_type not in (2, 6):
            kind = _PNG_KINDS.get(colour_type, "unknown")
            raise InputError(path, f"colour PNG must be 8-bit RGB or RGBA, found {bit_depth}-bit {kind}")
        size = width, height
    else:
        from PIL import Image   # opening reads the header only; the pixels stay undecoded
        try:
            with Image.open(path) as image:
                mode, size = image.mode, image.size
        except (OSError, ValueError, SyntaxError) as exc:
            raise InputError(path, f"cannot read colour frame ({exc.__class__.__name__})") from None
        if mode != "RGB":
            raise InputError(path, f"colour frame must be 8-bit with 3 channels, found mode {mode}")
    if min(size) <= 0:
        raise InputError(path, f"colour frame is {size[0]}x{size[1]}: empty")
    return size


def plan_color(layout: Layout, files: list[FrameFiles], depth_size: tuple[int, int],
               root: Path) -> tuple[tuple[int, int] | None, list[FrameFiles], tuple[str, ...]]:
    """The first used colour frame's (width, height) (None: colour is not used), the frames
    without the colour frames that cannot be used, and the notes the run prints about it (once
    each). Every colour frame's header is checked, like the depth's. A colour frame of another
    size than the depth is used resized where its aspect ratio is the depth's; where it is not,
    its frame runs without colour."""
    have = [f for f in files if f.color is not None]
    if not have:
        return None, files, ()
    if not layout.color_registered:
        return None, files, (f"{layout.name} colour frames are not registered to the depth image: colour is not used",)
    W, H = depth_size
    sizes = {f.index: color_header(f.color) for f in have}
    fits = {index: _maps_onto(size, depth_size) for index, size in sizes.items()}
    used = [f for f in have if fits[f.index]]
    if not used:
        w, h = sizes[have[0].index]
        return None, files, (f"colour frames are {w}x{h} and depth {W}x{H}, another aspect ratio: colour is not used",)
    notes = []
    resized = sorted({sizes[f.index] for f in used} - {depth_size})
    if resized:
        listed = ", ".join(f"{w}x{h}" for w, h in resized)
        notes.append(f"colour frames are {listed} and depth {W}x{H}: colour is resized to the depth size")
    unfit = [f for f in have if not fits[f.index]]
    if unfit:
        w, h = sizes[unfit[0].index]
        notes.append(f"{len(unfit)} colour frame(s) of another aspect ratio than the depth's {W}x{H} (first: "
                     f"{unfit[0].color}, {w}x{h}): their frames run without colour")
        files = [f if f.color is None or fits[f.index] else replace(f, color=None) for f in files]
    missing = [f for f in files if f.index not in sizes]
    if missing:
        first = root / layout.sibling["color"].format(missing[0].index)
        notes.append(f"{len(missing)} of {len(files)} frames have no colour frame (first: {first}); "
                     "they run without colour")
    return sizes[used[0].index], files, tuple(notes)


def _maps_onto(color_size: tuple[int, int], depth_size: tuple[int, int]) -> bool:
    """Whether a colour image of this (width, height) resizes onto the depth image: scaled to
    the depth's height, its width must be within half a pixel of the depth's, else no resize
    lines the two up everywhere."""
    (w, h), (W, H) = color_size, depth_size
    return abs(w * H / h - W) <= 0.5


class Sequence:
    """An opened depth sequence; frames are decoded one at a time by `frames()` (depth) and
    `read_color`. `notes` are what the run says once about the input (colour not used, ...)."""

    def __init__(self, root: Path, layout: str, intrinsics: Intrinsics, files: list[FrameFiles],
                 depth_scale: float, color_size: tuple[int, int] | None = None, notes: tuple[str, ...] = ()):
        self.root, self.layout, self.intrinsics = root, layout, intrinsics
        self.files, self.depth_scale = files, depth_scale
        self.color_size, self.notes = color_size, notes
        # Gaps in the frame numbers between the first and the last selected frame.
        present = {f.index for f in files}
        self.missing = [i for i in range(files[0].index, files[-1].index + 1) if i not in present] if files else []
        if self.missing:
            self.notes = self.notes + (f"{len(self.missing)} frame number(s) missing, the run goes on without "
                                       f"them: {_ranges(self.missing)}",)

    def __len__(self) -> int:
        return len(self.files)

    @property
    def has_color(self) -> bool:
        """Whether colour is used: registered to the depth, of a size that maps onto it."""
        return self.color_size is not None

    def read_depth(self, frame: FrameFiles) -> np.ndarray:
        """Depth in metres as float32, 0 where there is no measurement."""
        raw = _imread(frame.depth)
        if raw is None:
            raise InputError(frame.depth, "cannot decode depth PNG (file is damaged or unreadable)")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise InputError(frame.depth, f"depth PNG must be 16-bit single-channel, decoded as {raw.dtype} {raw.shape}")
        if raw.shape != (self.intrinsics.height, self.intrinsics.width):
            raise InputError(frame.depth, f"frame is {raw.shape[1]}x{raw.shape[0]}, expected "
                                          f"{self.intrinsics.width}x{self.intrinsics.height}")
        return raw.astype(np.float32) / np.float32(self.depth_scale)

    def read_color(self, frame: FrameFiles) -> np.ndarray | None:
        """(H, W, 3) uint8 RGB registered to the depth image (resized to it if need be); None
        when colour is not used or this frame has none."""
        if not self.has_color or frame.color is None:
            return None
        raw = _imread(frame.color)
        if raw is None:
            raise InputError(frame.color, "cannot decode colour frame (file is damaged or unreadable)")
        if raw.dtype != np.uint8 or raw.ndim != 3 or raw.shape[2] not in (3, 4):
            raise InputError(frame.color, f"colour frame must be 8-bit with 3 channels, decoded as "
                                          f"{raw.dtype} {raw.shape}")
        h, w = raw.shape[:2]
        size = (self.intrinsics.width, self.intrinsics.height)
        if not _maps_onto((w, h), size):    # its header said otherwise when the sequence was opened
            raise InputError(frame.color, f"colour frame is {w}x{h}, another aspect ratio than the depth's "
                                          f"{size[0]}x{size[1]}")
        rgb = cv2.cvtColor(raw, cv2.COLOR_BGRA2RGB if raw.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        return rgb if (w, h) == size else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)

    def read_pose(self, frame: FrameFiles) -> np.ndarray | None:
        """Ground-truth 4x4 camera-to-world pose where the layout has one."""
        if frame.pose is None:
            return None
        try:
            pose = np.loadtxt(frame.pose, dtype=np.float64).reshape(4, 4)
        except (OSError, ValueError):
            raise InputError(frame.pose, "pose file does not parse: expected a 4x4 matrix") from None
        return pose

    def frames(self) -> Iterator[tuple[FrameFiles, np.ndarray]]:
        """(files, depth) of every frame; the colour, where wanted, is read_color(files)."""
        for frame in self.files:
            yield frame, self.read_depth(frame)


def _ranges(numbers: list[int]) -> str:
    """'3, 7-9, 12' for [3, 7, 8, 9, 12]."""
    parts, start = [], None
    for i, n in enumerate(numbers):
        start = n if start is None else start
        if i + 1 == len(numbers) or numbers[i + 1] != n + 1:
            parts.append(f"{start}" if start == n else f"{start}-{n}")
            start = None
    return ", ".join(parts)


def _match_frames(root: Path, layout: Layout) -> list[tuple[int, Path]]:
    folder = root / "depth" if layout.depth_pattern.pattern.startswith("depth/") else root
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        m = layout.depth_pattern.fullmatch(path.relative_to(root).as_posix())
        if m:
            found.append((int(m.group(1)), path))
    return sorted(found)


def detect_layout(root: Path, have_intrinsics: bool) -> tuple[Layout, list[tuple[int, Path]], Path | None]:
    """The layout whose depth files and intrinsics file are both present.

    Without an intrinsics file, a layout still matches when --intrinsics was given.
    """
    fallback = None
    for layout in LAYOUTS:
        frames = _match_frames(root, layout)
        if not frames:
            continue
        intrinsics_files = sorted(root.glob(layout.intrinsics_glob))
        if intrinsics_files:
            return layout, frames, intrinsics_files[0]
        fallback = fallback or (layout, frames, None)
    if fallback is not None and have_intrinsics:
        return fallback
    if fallback is not None:
        raise InputError(root, f"found {fallback[0].name} depth frames but no intrinsics file "
                               f"({fallback[0].intrinsics_glob}); pass --intrinsics fx,fy,cx,cy")
    raise InputError(root, "matches no known sequence layout (expected frame-%06d.depth.png, "
                           "depth/%06d.png or depth_%06d.png; see CONTRACT.md)")


def open_sequence(path: str | Path, *, intrinsics: Intrinsics | None = None, depth_scale: float = 1000.0,
                  start: int = 0, max_frames: int | None = None) -> Sequence:
    """Detect the layout, read the intrinsics and check every selected frame's header.

    `start` is a frame index (the number in the file name); `max_frames` bounds the count.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputError(root, "input sequence folder does not exist" if not root.exists() else "input is not a folder")
    if not 0 < depth_scale < np.inf:
        raise InputError(None, f"--depth-scale must be positive and finite, got {depth_scale}")
    layout, frames, intrinsics_path = detect_layout(root, intrinsics is not None)
    given = intrinsics is not None
    if not given:
        intrinsics = parse_intrinsics_file(intrinsics_path)
    frames = [(i, p) for i, p in frames if i >= start]
    if max_frames is not None:
        frames = frames[:max_frames]
    if not frames:
        raise InputError(root, f"no depth frames at or after --start {start}")
    files = []
    size = None
    for index, depth_path in frames:
        size = _check_depth_header(depth_path, size)
        extra = {}
        for kind, pattern in layout.sibling.items():
            candidate = root / pattern.format(index)
            extra[kind] = candidate if candidate.exists() else None
        files.append(FrameFiles(index, depth_path, **extra))
    check_principal_point(intrinsics, None if given else intrinsics_path, *size)
    color_size, files, notes = plan_color(layout, files, size, root)
    return Sequence(root, layout.name, intrinsics.with_size(*size), files, depth_scale, color_size, notes)
