"""`surfelwarp` command line: run, batch, compare, bench, mesh, view, synth, eval (argparse only; the work is
elsewhere)."""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

from surfelwarp.errors import GLUnavailableError, InputError

METHODS = ("observe", "surfelwarp", "dynamicfusion")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def _frame_list(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frame numbers separated by commas, got {text!r}") from None


def _add_input_arguments(p: argparse.ArgumentParser, out_help: str, out_required: bool = True,
                         save_every: int = 10) -> None:
    """The flags `run`, `compare` and `bench` share: the input, its reading and preprocessing, the outputs."""
    p.add_argument("input", type=Path, help="sequence folder (any layout of docs/formats.md)")
    p.add_argument("--out", type=Path, required=out_required, default=None, help=out_help)
    _add_reading_arguments(p, save_every)
    p.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")


def _add_reading_arguments(p: argparse.ArgumentParser, save_every: int = 10) -> None:
    """How a sequence is read, preprocessed and saved (shared by run, compare, bench, batch)."""
    p.add_argument("--save-every", type=_positive_int, default=save_every, metavar="K",
                   help="write live/frame-%%06d.ply every K processed frames (and the last)")
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="override the intrinsics file")
    p.add_argument("--depth-scale", type=float, default=1000.0, help="PNG units per metre (default 1000)")
    p.add_argument("--clip-near", type=float, default=None, metavar="M", help="near clip, metres (default 0.1)")
    p.add_argument("--clip-far", type=float, default=None, metavar="M", help="far clip, metres (default 3.0)")
    p.add_argument("--start", type=int, default=0, metavar="FRAME", help="first frame index to process")
    p.add_argument("--max-frames", type=_positive_int, default=None, metavar="N")
    p.add_argument("--no-fusion", action="store_true",
                   help="SurfelWarp as template tracking: the first frame's surfels are tracked, never fused "
                        "or extended")


def _add_run_arguments(p: argparse.ArgumentParser) -> None:
    _add_input_arguments(p, "output folder")
    _add_method_arguments(p)
    p.add_argument("--resume", action="store_true",
                   help="continue the run OUT holds from its last checkpoint (same input and parameters; "
                        "--max-frames may be larger)")


def _add_method_arguments(p: argparse.ArgumentParser) -> None:
    """The method and its parameters (shared by run and batch)."""
    p.add_argument("--method", choices=METHODS, default="surfelwarp")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="the method's parameters to override, TOML or JSON (see docs/cli.md)")
    p.add_argument("--no-render", action="store_true",
                   help="no render/frame-%%06d.png pictures of the saved frames and no live.mp4")
    p.add_argument("--camera", choices=("moving", "static"), default=None,
                   help="'static': the camera does not move, every motion is the scene's; "
                        "'moving' (default): its pose is estimated (config key tracking.camera)")


def _add_compare_arguments(p: argparse.ArgumentParser) -> None:
    _add_input_arguments(p, "output folder (surfelwarp/, dynamicfusion/, report.md)")
    p.add_argument("--voxel-size", type=float, default=None, metavar="M",
                   help="DynamicFusion voxel size, metres (default 0.004)")
    p.add_argument("--graph-k", type=_positive_int, default=None, metavar="K",
                   help="both methods: regularise each node with its K nearest nodes (default 8); with "
                        "separate parts (fingers) K nearest may link across the gap between them")
    p.add_argument("--hierarchical", action="store_true",
                   help="DynamicFusion regularises through its hierarchical deformation tree")
    p.add_argument("--render-frames", type=_frame_list, default=None, metavar="F1,F2,..",
                   help="frames whose live models are rendered as normal maps (default: up to 3 saved ones)")


def _add_bench_arguments(p: argparse.ArgumentParser) -> None:
    _add_input_arguments(p, "keep the runs in this folder (default: a temporary one)", out_required=False,
                         save_every=100)
    p.add_argument("--compare-with", choices=("dynamicfusion",), default=None,
                   help="run the baseline on the same frames and print the speed ratios")
    p.add_argument("--open3d", action="store_true",
                   help="time Open3D's dense SLAM on the same frames (needs the 'bench' extra, open3d-cpu)")
    p.add_argument("--colour-cost", action="store_true",
                   help="run SurfelWarp again with the feature term off and print all the colour "
                        "tracking adds to a frame")


def _preprocess_params(args: argparse.Namespace):
    from surfelwarp.preprocess import PreprocessParams
    params = PreprocessParams()
    if args.clip_near is not None:
        params = replace(params, clip_near_m=args.clip_near)
    if args.clip_far is not None:
        params = replace(params, clip_far_m=args.clip_far)
    if not 0 <= params.clip_near_m < params.clip_far_m < float("inf"):
        raise InputError(None, f"--clip-near {params.clip_near_m} must be >= 0 and below --clip-far {params.clip_far_m}, "
                               "which must be finite")
    return params


def _intrinsics(args: argparse.Namespace):
    from surfelwarp.io.sequence import parse_intrinsics_flag
    return parse_intrinsics_flag(args.intrinsics) if args.intrinsics else None


def _params(args: argparse.Namespace):
    """The method's parameters: its defaults, --config, --camera (None: the observe method)."""
    if args.method == "observe":
        if args.config is not None:
            raise InputError(args.config, "--config sets a reconstruction method's parameters: the observe "
                                          "method has none")
        return None
    if args.method == "surfelwarp":
        from surfelwarp.methods.surfelwarp.params import SurfelWarpParams as Params
    else:
        from surfelwarp.methods.dynamicfusion.params import DynamicFusionParams as Params
    params = Params()
    if args.config is not None:
        from surfelwarp.config import load_params
        params = load_params(args.config, params)
    if args.camera is not None:
        params = replace(params, tracking=replace(params.tracking, camera=args.camera))
    return params


def _method(args: argparse.Namespace, params, intrinsics):
    if args.method == "surfelwarp":
        from surfelwarp.methods.surfelwarp.pipeline import SurfelWarpMethod
        return SurfelWarpMethod(intrinsics, params, fusion=not args.no_fusion)
    if args.method == "dynamicfusion":
        from surfelwarp.methods.dynamicfusion.pipeline import DynamicFusionMethod
        return DynamicFusionMethod(intrinsics, params)
    from surfelwarp.methods.observe import ObserveMethod
    return ObserveMethod()


def _check_folder(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")


def check_out_folder(input_path: Path, out: Path) -> Path:
    """OUT, if it can hold a run's outputs: a folder (or nothing yet), not INPUT nor inside it."""
    _check_folder(out)
    inp, target = input_path.resolve(), out.resolve()
    if target == inp or inp in target.parents:
        raise InputError(out, f"output folder is the input folder {input_path} or lies inside it; "
                              f"choose another --out")
    return out


def prepare_run(args: argparse.Namespace) -> dict:
    """`run`'s flags checked and turned into run_sequence's arguments (the sequence opened, the
    method built): the keyword arguments of run_sequence without `resume`."""
    from surfelwarp.io.sequence import open_sequence
    from surfelwarp.run import input_config

    params = _params(args)
    preprocess = _preprocess_params(args)
    out = check_out_folder(args.input, args.out)
    seq = open_sequence(args.input, intrinsics=_intrinsics(args), depth_scale=args.depth_scale,
                        start=args.start, max_frames=args.max_frames)
    return dict(seq=seq, out_dir=out, method=_method(args, params, seq.intrinsics), save_every=args.save_every,
                preprocess_params=preprocess, input_config=input_config(seq, args.start, args.max_frames),
                progress=False if args.no_progress else None, render=not args.no_render)


def cmd_run(args: argparse.Namespace) -> int:
    from surfelwarp.run import run_sequence

    setup = prepare_run(args)
    s = run_sequence(**setup, resume=args.resume).summary()
    print(f"{s['frames']} frames, median {s['median_frame_seconds'] * 1000:.0f} ms/frame, "
          f"peak {s['peak_rss_mb']:.0f} MB; outputs in {setup['out_dir']}/ (live/, model.ply, metrics.json)")
    return 0


def compare_spec(args: argparse.Namespace):
    """The comparison's CompareSpec from its flags."""
    from surfelwarp.methods.dynamicfusion.params import DynamicFusionParams

    df = DynamicFusionParams()
    if args.hierarchical:
        df = replace(df, tracking=replace(df.tracking, hierarchy=replace(df.tracking.hierarchy, enabled=True)))
    if args.voxel_size is not None:
        if not 0 < args.voxel_size < 1:
            raise InputError(None, f"--voxel-size must be in (0, 1) metres, got {args.voxel_size}")
        # The truncation band keeps its width in voxels (3, as the defaults 12 mm / 4 mm).
        df = replace(df, tsdf=replace(df.tsdf, voxel_size_m=args.voxel_size, truncation_m=3 * args.voxel_size))
    sw_field = None
    if args.graph_k is not None:
        from surfelwarp.config import range_problem
        problem = range_problem(replace(df.warp_field, graph_k=args.graph_k), "graph_k")
        if problem:
            raise InputError(None, f"--graph-k {problem}")
        df = replace(df, warp_field=replace(df.warp_field, graph_k=args.graph_k))
        sw_field = df.warp_field
    return _input_spec(args, dynamicfusion=df, surfelwarp_warp_field=sw_field)


def _input_spec(args: argparse.Namespace, **methods):
    """The CompareSpec of the shared input flags (_add_input_arguments), plus `methods`' fields."""
    from surfelwarp.report.runner import CompareSpec
    return CompareSpec(input=args.input, out=args.out, intrinsics=_intrinsics(args), depth_scale=args.depth_scale,
                       start=args.start, max_frames=args.max_frames, save_every=args.save_every,
                       preprocess=_preprocess_params(args), surfelwarp_fusion=not args.no_fusion,
                       progress=False if args.no_progress else None, **methods)


def cmd_compare(args: argparse.Namespace) -> int:
    from surfelwarp.report.compare import compare
    check_out_folder(args.input, args.out)
    report = compare(compare_spec(args), args.render_frames)
    print(f"comparison written to {report}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from surfelwarp.report.bench import bench

    if args.out is not None:
        check_out_folder(args.input, args.out)
    print(bench(_input_spec(args), args.compare_with, args.open3d, args.colour_cost))
    return 0


def cmd_mesh(args: argparse.Namespace) -> int:
    from surfelwarp.report.mesh import mesh_run
    path = mesh_run(args.out, args.frame, args.voxel_size)
    print(f"mesh written to {path}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from surfelwarp.report.viewer import write_viewer
    if not 0 < args.max_points:
        raise InputError(None, f"--max-points must be positive, got {args.max_points}")
    path = write_viewer(args.out, args.html, args.max_points)
    print(f"viewer written to {path} (open it in a browser)")
    return 0


def _run_options() -> argparse.ArgumentParser:
    """The run flags a batch passes on to each sequence's run."""
    p = argparse.ArgumentParser(add_help=False)
    _add_reading_arguments(p)
    _add_method_arguments(p)
    return p


def run_flags(args: argparse.Namespace) -> list[str]:
    """The run flags given in `args` (those that differ from their defaults), as argv."""
    flags = []
    for action in _run_options()._actions:
        value = getattr(args, action.dest)
        if value == action.default:
            continue
        flag = action.option_strings[0]
        if isinstance(value, Path):     # the workers may run elsewhere: no relative paths
            value = value.resolve()
        if action.nargs == 0:           # a switch (store_true)
            flags.append(flag)
        else:
            flags += [flag, ",".join(map(str, value)) if isinstance(value, list) else str(value)]
    return flags


def batch_setup(flags: list[str], input_path: str, out: str) -> dict:
    """prepare_run of `run INPUT --out OUT FLAGS` (on a batch's worker)."""
    return prepare_run(build_parser().parse_args(["run", input_path, "--out", out, "--no-progress", *flags]))


def cmd_batch(args: argparse.Namespace) -> int:
    from functools import partial

    from surfelwarp.batch import batch

    for path in args.inputs:     # DIR inside an INPUT would write into that input
        check_out_folder(path, args.out)
    _params(args), _preprocess_params(args), _intrinsics(args)   # bad flags end the batch before it starts
    results = batch(args.inputs, args.out, partial(batch_setup, run_flags(args)), args.workers, args.scheduler,
                    False if args.no_progress else None)
    counts = {s: sum(r.status == s for r in results) for s in ("done", "skipped", "failed")}
    print(f"{len(results)} sequences: {counts['done']} done, {counts['skipped']} skipped, {counts['failed']} failed; "
          f"summary in {args.out / 'summary.csv'}")
    return 1 if counts["failed"] else 0


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one line (CONTRACT.md: one clear message), not after
    the usage block; subcommands' parsers are of this class too."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="surfelwarp", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="reconstruct a depth sequence")
    _add_run_arguments(p)
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("compare", help="run SurfelWarp and DynamicFusion on the same frames, write report.md")
    _add_compare_arguments(p)
    p.set_defaults(func=cmd_compare)
    p = sub.add_parser("bench", help="time a sequence stage by stage (and against DynamicFusion, Open3D)")
    _add_bench_arguments(p)
    p.set_defaults(func=cmd_bench)
    p = sub.add_parser("batch", parents=[_run_options()],
                       help="many sequences at once on Dask, each as `run` would (DIR/<name>/, DIR/summary.csv)")
    p.add_argument("inputs", type=Path, nargs="+", metavar="INPUT", help="sequence folders")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="one sub-folder per sequence, and the summary")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_int, default=os.cpu_count() or 1, metavar="N",
                       help="worker processes of a local Dask cluster (default: the machine's cores)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (dask scheduler / dask worker)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    p.set_defaults(func=cmd_batch)
    p = sub.add_parser("mesh", help="a triangle mesh of a run's model (model_mesh.ply) or of a saved live frame")
    p.add_argument("out", type=Path, help="a run's output folder")
    p.add_argument("--frame", type=int, default=None, metavar="N",
                   help="mesh OUT/live/frame-N.ply into OUT/mesh/frame-N.ply (default: model.ply)")
    p.add_argument("--voxel-size", type=float, default=None, metavar="M",
                   help="grid spacing, metres (default: the surfels' median radius)")
    p.set_defaults(func=cmd_mesh)
    p = sub.add_parser("view", help="a self-contained HTML page showing the saved live frames")
    p.add_argument("out", type=Path, help="a run's output folder")
    p.add_argument("--html", type=Path, default=None, help="page to write (default OUT/view.html)")
    p.add_argument("--max-points", type=int, default=150_000, metavar="N",
                   help="points over all frames at most (uniformly subsampled)")
    p.set_defaults(func=cmd_view)
    try:
        from surfelwarp.data_tools import evaluate, synth
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
    except (InputError, GLUnavailableError) as exc:
        print(f"surfelwarp: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("surfelwarp: interrupted; outputs written so far are complete", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
