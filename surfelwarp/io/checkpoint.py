"""OUT/checkpoint.pkl: the whole state of a run after a saved frame, so `run --resume` can go on.

The method object is pickled whole (surfel model or volume, warp field, tracker with its pose
history, anchors and colour keyframe, reinitialisation trigger, id counter): whatever a method
keeps between frames is in it, so a resumed run continues exactly where the uninterrupted one
would be. GL resources are not part of a method's state (render/context.py owns them). The
file is written atomically (temporary file, rename), and names the run it belongs to:
the input folder, the method and every parameter in force except how many frames were asked
for, so a run can be resumed with a larger --max-frames but not with other settings.

Pickle runs code from the file it loads: a checkpoint is trusted as the output folder it lives
in is (it is this program's own file); it is not an exchange format.
"""
from __future__ import annotations

import json
import pickle
from dataclasses import dataclass, field
from pathlib import Path

from surfelwarp.errors import InputError
from surfelwarp.io.ply import write_atomic_with

FORMAT = 2     # 2: the tracker keeps what the read-ahead found (a format-1 method lacks it)
NAME = "checkpoint.pkl"


@dataclass
class Checkpoint:
    identity: dict            # run_identity() of the run that wrote it
    next_position: int        # index among the sequence's selected frames of the next one to process
    method: object            # the reconstruction method, whole
    frames: list = field(default_factory=list)     # FrameRecord of every processed frame so far
    skipped: list = field(default_factory=list)    # frame numbers skipped before the model started
    format: int = FORMAT


def run_identity(method: str, input_path: Path, config: dict) -> dict:
    """What a checkpoint must match to be resumed: the run's config without its frame count,
    as JSON values (tuples become lists)."""
    config = json.loads(json.dumps(config))
    config.get("input", {}).pop("max_frames", None)
    return {"method": method, "input": str(Path(input_path).resolve()), "config": config}


def _first_difference(a, b, prefix: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            found = _first_difference(a.get(key), b.get(key), f"{prefix}{key}.")
            if found:
                return found
        return None
    return None if a == b else f"{prefix.rstrip('.')} ({a!r} there, {b!r} now)"


def save(out_dir: Path, checkpoint: Checkpoint) -> Path:
    path = Path(out_dir) / NAME
    write_atomic_with(path, lambda f: pickle.dump(checkpoint, f, protocol=pickle.HIGHEST_PROTOCOL))
    return path


def load(out_dir: Path, identity: dict) -> Checkpoint:
    """The checkpoint in out_dir if it belongs to the run `identity` describes; else InputError."""
    path = Path(out_dir) / NAME
    if not path.is_file():
        raise InputError(path, "nothing to resume: no checkpoint (a run writes one with every saved frame)")
    try:
        with open(path, "rb") as f:
            checkpoint = pickle.load(f)
    except Exception as exc:      # a damaged file can fail in any unpickling step
        raise InputError(path, f"checkpoint cannot be read ({exc.__class__.__name__}); run again without --resume") \
            from None
    if not isinstance(checkpoint, Checkpoint) or checkpoint.format != FORMAT:
        raise InputError(path, "checkpoint was written by another version of surfelwarp; run again without --resume")
    difference = _first_difference(checkpoint.identity, identity)
    if difference:
        raise InputError(path, f"checkpoint belongs to another run: {difference}")
    return checkpoint
