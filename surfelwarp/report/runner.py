"""Running both methods on the same frames, each in a fresh process (its peak memory its own)."""
from __future__ import annotations

import pickle
import subprocess
import sys
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

from surfelwarp.errors import InputError
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.preprocess import PreprocessParams


METHODS = ("surfelwarp", "dynamicfusion")
LABELS = {"surfelwarp": "SurfelWarp", "dynamicfusion": "DynamicFusion"}


def make_surfelwarp(intrinsics: Intrinsics, warp_field=None, fusion: bool = True, colour: bool = True):
    """The full pipeline, or template tracking with fusion=False; warp_field: WarpFieldParams
    replacing SurfelWarp's default (None keeps it); colour=False: the feature term off, so the
    tracker does no colour work (as `[tracking.nonrigid] feature_weight = 0`; the surfels still
    fuse the colour)."""
    from surfelwarp.methods.surfelwarp.pipeline import SurfelWarpMethod, SurfelWarpParams
    params = SurfelWarpParams() if warp_field is None else replace(SurfelWarpParams(), warp_field=warp_field)
    if not colour:
        tracking = params.tracking
        params = replace(params, tracking=replace(tracking, nonrigid=replace(tracking.nonrigid, feature_weight=0.0)))
    return SurfelWarpMethod(intrinsics, params, fusion=fusion)


def make_dynamicfusion(intrinsics: Intrinsics, params=None):
    from surfelwarp.methods.dynamicfusion.pipeline import DynamicFusionMethod, DynamicFusionParams
    return DynamicFusionMethod(intrinsics, params or DynamicFusionParams())


@dataclass(frozen=True)
class CompareSpec:
    """Everything a run needs, picklable for the child process."""
    input: Path
    out: Path
    intrinsics: Intrinsics | None = None       # None: the sequence's intrinsics file
    depth_scale: float = 1000.0
    start: int = 0
    max_frames: int | None = None
    save_every: int = 10
    preprocess: PreprocessParams = PreprocessParams()
    dynamicfusion: object | None = None        # DynamicFusionParams, None = defaults
    surfelwarp_warp_field: object | None = None  # WarpFieldParams for SurfelWarp, None = its default
    surfelwarp_fusion: bool = True  # False: SurfelWarp as template tracking
    surfelwarp_colour: bool = True  # False: SurfelWarp without the feature term (colour not matched)
    progress: bool | None = False


def open_input(spec: CompareSpec):
    from surfelwarp.io.sequence import open_sequence
    return open_sequence(spec.input, intrinsics=spec.intrinsics, depth_scale=spec.depth_scale,
                         start=spec.start, max_frames=spec.max_frames)


def run_method(name: str, spec: CompareSpec) -> tuple[str, str] | None:
    """Run one method into spec.out / name (in the child). Returns (path, problem) of an
    InputError (which does not pickle), else None."""
    from surfelwarp.run import input_config, run_sequence
    try:
        seq = open_input(spec)
        if name == "surfelwarp":
            method = make_surfelwarp(seq.intrinsics, spec.surfelwarp_warp_field, spec.surfelwarp_fusion,
                                     spec.surfelwarp_colour)
        else:
            method = make_dynamicfusion(seq.intrinsics, spec.dynamicfusion)
        run_sequence(seq, spec.out / name, method, save_every=spec.save_every, preprocess_params=spec.preprocess,
                     input_config=input_config(seq, spec.start, spec.max_frames), progress=spec.progress)
    except InputError as exc:
        return (None if exc.path is None else str(exc.path)), exc.problem
    return None


def child_main() -> int:
    """Entry of the child process: argv = [result file]; (name, spec) pickled on stdin."""
    name, spec = pickle.load(sys.stdin.buffer)
    error = run_method(name, spec)
    Path(sys.argv[1]).write_bytes(pickle.dumps(error))
    return 0


def run_in_child(name: str, spec: CompareSpec) -> None:
    """run_method in a fresh interpreter: its peak RSS is that method's alone, and it owns its
    GL context. (A plain subprocess rather than multiprocessing, which would re-import the
    caller's __main__ script.)"""
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.pickle"
        code = "import sys; from surfelwarp.report.runner import child_main; sys.exit(child_main())"
        proc = subprocess.run([sys.executable, "-c", code, str(result)], input=pickle.dumps((name, spec)))
        if proc.returncode != 0 or not result.exists():
            raise RuntimeError(f"the {name} run failed (exit status {proc.returncode}); see its messages above")
        error = pickle.loads(result.read_bytes())
    if error is not None:
        raise InputError(*error)
