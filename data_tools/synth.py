"""`surfelwarp synth`: synthetic depth sequences of deforming meshes, with ground truth.

Output folder (VolumeDeform layout, loads with surfelwarp.sequence.open_sequence):

    frame-%06d.depth.png   16-bit depth in millimetres, 0 = no measurement
    frame-%06d.color.png   8-bit RGB registered to the depth (same camera): a texture bound to
                           the material, Lambertian shading from a lamp beside the camera
                           (data_tools.texture)
    depthIntrinsics.txt    4x4 camera matrix (fx fy cx cy)
    groundtruth.npz        numpy archive:
        vertices         (F, V, 3) float32  the mesh of every frame in that frame's camera
                                            coordinates; vertex i is the same material point
                                            in every frame (dense correspondence)
        faces            (T, 3) int32       triangles, shared by all frames
        moving           (V,) bool          vertex moves in the scene (False: static wall,
                                            or everything when only the camera moves)
        part             (V,) int16         piece number (e.g. wall 0, tube 1; finger 0/1)
        camera_to_world  (F, 4, 4) float64  world = camera frame of the first frame
        frames           (F,) int32         frame index of each entry (the file number)
        intrinsics       (4,) float64       fx, fy, cx, cy
        size             (2,) int32         width, height
        scene, noise     str;  seed int;  depth_scale float (1000)

Camera: fx = fy = 550 * width / 640 (the same field of view at any size), cx, cy at the
image centre ((W-1)/2, (H-1)/2 with pixel (0, 0) = top-left pixel centre).
Noise: `kinect` (see data_tools.noise; colour gets Gaussian 8-bit noise) or `none` (clean depth
rounded to millimetres, colour without noise).
Per-frame random numbers come from numpy's generator seeded with (seed, frame).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from surfelwarp.errors import InputError
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import invert

from .meshes import edges, vertex_normals
from .noise import kinect_noise
from .render import MeshRenderer, incidence_cosine
from .scenes import SCENES
from .texture import LIGHTS, light_direction, shade

DEPTH_SCALE = 1000.0
NOISE_MODELS = ("kinect", "none")


def default_intrinsics(size: tuple[int, int]) -> Intrinsics:
    w, h = size
    f = 550.0 * w / 640.0
    return Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)


@dataclass(frozen=True)
class GroundTruth:
    vertices: np.ndarray
    faces: np.ndarray
    moving: np.ndarray
    part: np.ndarray
    camera_to_world: np.ndarray
    frames: np.ndarray
    intrinsics: Intrinsics
    scene: str

    def index(self, frame: int) -> int:
        hits = np.nonzero(self.frames == frame)[0]
        if len(hits) == 0:
            raise KeyError(frame)
        return int(hits[0])


def load_groundtruth(seq_dir: str | Path) -> GroundTruth:
    path = Path(seq_dir) / "groundtruth.npz"
    try:
        with np.load(path) as z:
            fx, fy, cx, cy = z["intrinsics"]
            w, h = z["size"]
            return GroundTruth(z["vertices"], z["faces"], z["moving"], z["part"], z["camera_to_world"],
                               z["frames"], Intrinsics(fx, fy, cx, cy, int(w), int(h)), str(z["scene"]))
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(path, f"cannot read ground truth ({exc.__class__.__name__}: {exc})") from None


def scene_frames(scene: str, frames: int):
    """(camera-frame vertices (F, V, 3) float32, camera_to_world (F, 4, 4), animation)."""
    anim = SCENES[scene].build()
    cam_to_scene = np.stack([anim.camera(i) for i in range(frames)])
    scene_to_cam = invert(cam_to_scene)
    vertices = np.empty((frames, len(anim.part), 3), np.float32)
    for i in range(frames):
        p = anim.positions(i)
        vertices[i] = p @ scene_to_cam[i, :3, :3].T + scene_to_cam[i, :3, 3]
    return vertices, invert(cam_to_scene[0]) @ cam_to_scene, anim


def motion_stats(vertices: np.ndarray, faces: np.ndarray, moving: np.ndarray, camera_to_world: np.ndarray) -> dict:
    """Largest edge strain against frame 0, largest per-frame vertex step (world frame), and
    the longest edge among moving vertices."""
    e = edges(faces)
    c2w = camera_to_world.astype(np.float32)
    world = vertices @ c2w[:, :3, :3].transpose(0, 2, 1) + c2w[:, None, :3, 3]
    step = np.linalg.norm(np.diff(world, axis=0), axis=-1).max() if len(world) > 1 else 0.0
    on_moving = moving[e[:, 0]] | moving[e[:, 1]]      # edges between static vertices keep their length
    e = e[on_moving] if on_moving.any() else e
    lengths = np.linalg.norm(world[:, e[:, 0]] - world[:, e[:, 1]], axis=-1)
    strain = np.abs(lengths / lengths[:1] - 1).max()
    return {"max_strain": float(strain), "max_step_m": float(step), "max_edge_m": float(lengths[0].max())}


def depth_to_png(depth_m: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(depth_m * DEPTH_SCALE), 0, 65535).astype(np.uint16)


def _prepare_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    old = sorted(out.glob("frame-*.depth.png"))
    if old and not (out / "groundtruth.npz").exists():
        raise InputError(out, "folder already holds depth frames that synth did not write; choose another --out")
    for path in old + sorted(out.glob("frame-*.color.png")):   # a previous synth run's frames
        path.unlink()


def generate(scene: str, out_dir, frames: int | None = None, size=(640, 480), noise: str = "kinect",
             seed: int = 0, progress: bool = False, light: str = "camera") -> Path:
    """Render `scene` into `out_dir` (created) and write its ground truth; returns the folder.
    `light`: the lamp beside the camera or left in the room (texture.light_direction)."""
    if scene not in SCENES:
        raise InputError(None, f"unknown scene {scene!r}; choose one of: {', '.join(SCENES)}")
    if noise not in NOISE_MODELS:
        raise InputError(None, f"unknown noise model {noise!r}; choose kinect or none")
    if light not in LIGHTS:
        raise InputError(None, f"unknown light {light!r}; choose {' or '.join(LIGHTS)}")
    frames = SCENES[scene].default_frames if frames is None else int(frames)
    w, h = (int(x) for x in size)
    if frames < 1 or w < 8 or h < 8:
        raise InputError(None, f"need at least one frame and 8x8 pixels, got {frames} frames of {w}x{h}")
    out = Path(out_dir)
    _prepare_out(out)
    intr = default_intrinsics((w, h))
    vertices, camera_to_world, anim = scene_frames(scene, frames)
    material = anim.positions(0)               # the texture is painted on the first frame's shape
    renderer = MeshRenderer(intr)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=frames, unit="frame", leave=False)
    try:
        for i in range(frames):
            normals = vertex_normals(vertices[i], anim.faces)
            depth, normal_map, material_map = renderer.render_maps(vertices[i], anim.faces, material, normals)
            # The colour noise has a stream of its own: the depth noise stays what it was before
            # synth wrote colour.
            color = shade(depth, normal_map, material_map,
                          np.random.default_rng([seed, i, 1]) if noise == "kinect" else None,
                          light=light_direction(light, camera_to_world[i], camera_to_world[0]), plain=anim.plain)
            if noise == "kinect":
                rng = np.random.default_rng([seed, i])
                depth = kinect_noise(depth, incidence_cosine(normal_map, intr), intr, rng)
            cv2.imwrite(str(out / f"frame-{i:06d}.depth.png"), depth_to_png(depth))
            cv2.imwrite(str(out / f"frame-{i:06d}.color.png"), color[..., ::-1])
            if bar is not None:
                bar.update()
    finally:
        renderer.release()
        if bar is not None:
            bar.close()
    K = np.eye(4)
    K[:3, :3] = intr.K
    np.savetxt(out / "depthIntrinsics.txt", K, fmt="%.6f")
    np.savez(out / "groundtruth.npz", vertices=vertices, faces=anim.faces, moving=anim.moving, part=anim.part,
             camera_to_world=camera_to_world, frames=np.arange(frames, dtype=np.int32),
             intrinsics=np.array([intr.fx, intr.fy, intr.cx, intr.cy]), size=np.array([w, h], np.int32),
             scene=np.array(scene), noise=np.array(noise), seed=np.array(seed), depth_scale=np.array(DEPTH_SCALE),
             light=np.array(light))
    return out


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x480, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"image must be at least 8x8 pixels, got {text!r}")
    return w, h


def _frames(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", nargs="?", help="scene name (see --list)")
    parser.add_argument("--out", type=Path, help="output folder")
    parser.add_argument("--frames", type=_frames, default=None, metavar="N", help="frame count (default: the scene's)")
    parser.add_argument("--size", type=_size, default=(640, 480), metavar="WxH", help="image size (default 640x480)")
    parser.add_argument("--noise", choices=NOISE_MODELS, default="kinect", help="sensor noise model (default kinect)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument("--light", choices=LIGHTS, default="camera",
                        help="the lamp beside the camera or left where it stood in the first frame (default camera)")
    parser.add_argument("--list", action="store_true", help="list the scenes and exit")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.list:
        for s in SCENES.values():
            print(f"{s.name:<10} {s.description} ({s.default_frames} frames)")
        return 0
    if args.scene is None or args.out is None:
        raise InputError(None, "synth needs a SCENE and --out DIR (or --list)")
    if args.scene not in SCENES:
        raise InputError(None, f"unknown scene {args.scene!r}; choose one of: {', '.join(SCENES)}")
    start = time.perf_counter()
    out = generate(args.scene, args.out, args.frames, args.size, args.noise, args.seed,
                   progress=not args.no_progress and sys.stderr.isatty(), light=args.light)
    gt = load_groundtruth(out)
    stats = motion_stats(gt.vertices, gt.faces, gt.moving, gt.camera_to_world)
    print(f"{args.scene}: {len(gt.frames)} frames {gt.intrinsics.width}x{gt.intrinsics.height}, noise {args.noise}, "
          f"{time.perf_counter() - start:.1f} s; max strain {100 * stats['max_strain']:.1f} %, "
          f"max step {1000 * stats['max_step_m']:.0f} mm/frame; written to {out}/")
    return 0
