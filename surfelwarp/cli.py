"""`surfelwarp` command line: run, synth, eval, compare."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import GLUnavailableError, InputError

METHODS = ("observe", "surfelwarp", "dynamicfusion")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="sequence folder (any layout of CONTRACT.md)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--method", choices=METHODS, default="surfelwarp")
    p.add_argument("--save-every", type=_positive_int, default=10, metavar="K",
                   help="write live/frame-%%06d.ply every K processed frames (and the last)")
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="override the intrinsics file")
    p.add_argument("--depth-scale", type=float, default=1000.0, help="PNG units per metre (default 1000)")
    p.add_argument("--clip-near", type=float, default=None, metavar="M", help="near clip, metres (default 0.1)")
    p.add_argument("--clip-far", type=float, default=None, metavar="M", help="far clip, metres (default 3.0)")
    p.add_argument("--start", type=int, default=0, metavar="FRAME", help="first frame index to process")
    p.add_argument("--max-frames", type=_positive_int, default=None, metavar="N")
    p.add_argument("--no-fusion", action="store_true",
                   help="template tracking: the first frame's surfels are tracked, never fused or extended")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="SurfelWarp parameters to override, TOML or JSON (see surfelwarp/config.py)")
    p.add_argument("--camera", choices=("moving", "static"), default=None,
                   help="'static': the camera does not move, every motion is the scene's; "
                        "'moving' (default): its pose is estimated (config key tracking.camera)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")


def _with_camera(params, camera: str | None):
    """params (with a `tracking` tree) with tracking.camera set by --camera, if given."""
    from dataclasses import replace
    return params if camera is None else replace(params, tracking=replace(params.tracking, camera=camera))


def cmd_run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from .observation import PreprocessParams
    from .observe import ObserveMethod
    from .run import run_sequence
    from .sequence import open_sequence, parse_intrinsics_flag

    sw_params = None
    if args.config is not None:
        if args.method != "surfelwarp":
            raise InputError(args.config, "--config sets SurfelWarp parameters: use it with --method surfelwarp")
        from .config import load_params
        sw_params = load_params(args.config)
    intrinsics = parse_intrinsics_flag(args.intrinsics) if args.intrinsics else None
    seq = open_sequence(args.input, intrinsics=intrinsics, depth_scale=args.depth_scale,
                        start=args.start, max_frames=args.max_frames)
    params = PreprocessParams()
    if args.clip_near is not None:
        params = replace(params, clip_near_m=args.clip_near)
    if args.clip_far is not None:
        params = replace(params, clip_far_m=args.clip_far)
    if not 0 <= params.clip_near_m < params.clip_far_m:
        raise InputError(None, f"--clip-near {params.clip_near_m} must be >= 0 and below --clip-far {params.clip_far_m}")
    out = args.out
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    if args.method == "surfelwarp":
        from .pipeline import SurfelWarpMethod, SurfelWarpParams
        sw_params = _with_camera(sw_params or SurfelWarpParams(), args.camera)
        method = SurfelWarpMethod(seq.intrinsics, sw_params, fusion=not args.no_fusion)
    elif args.method == "dynamicfusion":
        from .dynamicfusion import DynamicFusionMethod, DynamicFusionParams
        method = DynamicFusionMethod(seq.intrinsics, _with_camera(DynamicFusionParams(), args.camera))
    else:
        method = ObserveMethod()
    input_config = {"layout": seq.layout, "depth_scale": seq.depth_scale, "start": args.start,
                    "max_frames": args.max_frames, "intrinsics": {
                        k: getattr(seq.intrinsics, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}}
    outputs = run_sequence(seq, out, method, save_every=args.save_every, preprocess_params=params,
                           input_config=input_config, progress=False if args.no_progress else None)
    s = outputs.summary()
    print(f"{s['frames']} frames, median {s['median_frame_seconds'] * 1000:.0f} ms/frame, "
          f"peak {s['peak_rss_mb']:.0f} MB; outputs in {out}/ (live/, model.ply, metrics.json)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="surfelwarp", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="reconstruct a depth sequence")
    _add_run_arguments(run)
    run.set_defaults(func=cmd_run)
    from . import compare
    p = sub.add_parser("compare", help="run SurfelWarp and DynamicFusion on the same frames, write report.md")
    compare.add_arguments(p)
    p.set_defaults(func=compare.run)
    try:
        from .data_tools import evaluate, synth
    except ImportError:
        pass
    else:
        p = sub.add_parser("synth", help="render a synthetic sequence with ground truth")
        synth.add_arguments(p)
        p.set_defaults(func=synth.run)
        p = sub.add_parser("eval", help="evaluate a run against a sequence's ground truth")
        evaluate.add_arguments(p)
        p.set_defaults(func=evaluate.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"surfelwarp: error: {exc}", file=sys.stderr)
        return 2
    except GLUnavailableError as exc:
        print(f"surfelwarp: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("surfelwarp: interrupted; outputs written so far are complete", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
