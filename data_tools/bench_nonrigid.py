"""Benchmark of the non-rigid Gauss-Newton solve on a rendered synthetic scene.

    python -m surfelwarp.data_tools.bench_nonrigid [--scene tube-wall] [--size 640x480] [--frame 2]

Renders frames 0..F of the scene (data_tools.synth), takes the valid pixels of frame 0 as the
model surfels (world = camera 0), samples nodes on them and solves for the warp to frame F at
its true camera pose, starting from the identity field. Prints the median time of every part of
one Gauss-Newton iteration and of whole solves, with the solve's iterations and energies. The
machine may be shared: compare medians of several repeats.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, apply_update, skin
from surfelwarp.io.sequence import open_sequence
from surfelwarp.preprocess import preprocess
from surfelwarp.tracking.gauss_newton import NonRigidParams, Solve, solve_nonrigid
from surfelwarp.tracking.linear import solve_step, solve_step_pcg
from surfelwarp.tracking.terms import Problem

from .synth import generate, load_groundtruth


def build_problem(scene: str, size: tuple[int, int], frame: int, node_radius_m: float, stride: int, out: Path):
    generate(scene, out, frames=frame + 1, size=size)
    seq = open_sequence(out)
    gt = load_groundtruth(out)
    depths = [d for _, d in seq.frames()]
    first = preprocess(depths[0], seq.intrinsics, 0, 0)
    last = preprocess(depths[frame], seq.intrinsics, frame, frame)
    pts, nrm = first.vertex_map[first.valid][::stride], first.normal_map[first.valid][::stride]
    field = WarpField.from_points(pts, WarpFieldParams(node_radius_m=node_radius_m))
    knn, w = skin(pts, field.nodes, field.params.k_skin, field.sigma_m)
    maps = (last.vertex_map, last.normal_map, last.valid, seq.intrinsics, gt.camera_to_world[frame])
    return field, (pts, nrm, knn, w), maps


def _components(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, np.float64).T)


def _timed(times: dict, name: str, fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    times.setdefault(name, []).append(time.perf_counter() - t0)
    return out


def one_iteration(field, model, maps, params, times, stats):
    """The parts of one Gauss-Newton iteration at `field`, timed one by one."""
    pts, nrm, knn, w = model
    problem = Problem(field, _components(pts), _components(nrm), np.asarray(knn, np.int64),
                      np.asarray(w, np.float64), *maps, params)
    solve = _timed(times, "depth maps to world, terms (once)", Solve, problem)
    _timed(times, "block pattern (once per solve)", solve.pattern_for, field)
    at = _timed(times, "warp + associate", solve.at, field)
    energy = _timed(times, "energy", solve.energy, at)
    _, system = _timed(times, "jacobian + normal equations", solve.linearize, at, np.ones(field.num_nodes, bool))
    pattern = system.pattern
    H, g, diag = pattern.matrix(system.upper), system.gradient.reshape(-1), system.upper[pattern.diag]
    exact = _timed(times, "solve step (direct, fallback)", solve_step, H, g, params.damping)
    xi, its, _ = _timed(times, "solve step (pcg)", solve_step_pcg, H, g, params.damping, params.pcg_rtol,
                        params.pcg_max_iterations, diag)
    stats.setdefault("pcg iterations", []).append(its)
    stats.setdefault("pcg step vs direct, relative", []).append(
        float(np.linalg.norm(xi - exact) / max(np.linalg.norm(exact), 1e-300)))
    stats.setdefault("energy at the identity", []).append(energy)
    _timed(times, "apply update", apply_update, field, xi.reshape(-1, 6))
    return len(at.pairs.index)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="tube-wall")
    ap.add_argument("--size", default="640x480", help="WxH of the rendered frames")
    ap.add_argument("--frame", type=int, default=2, help="solve from frame 0 to this frame")
    ap.add_argument("--node-radius", type=float, default=0.025, help="node spacing, m")
    ap.add_argument("--stride", type=int, default=1, help="use every n-th valid pixel of frame 0 as a surfel")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--solves", type=int, default=3, help="whole solves to time")
    ap.add_argument("--max-iterations", type=int, default=NonRigidParams().max_iterations)
    ap.add_argument("--solver", choices=("pcg", "direct"), default=None, help="linear solver of whole solves")
    ap.add_argument("--pcg-rtol", type=float, default=None)
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    extra = {k: v for k, v in (("linear_solver", args.solver), ("pcg_rtol", args.pcg_rtol)) if v is not None}
    params = NonRigidParams(max_iterations=args.max_iterations, **extra)

    with tempfile.TemporaryDirectory() as tmp:
        field, model, maps = build_problem(args.scene, size, args.frame, args.node_radius, args.stride, Path(tmp))
    print(f"{args.scene} {size[0]}x{size[1]}, frame 0 -> {args.frame}: {len(model[0])} surfels, "
          f"{field.num_nodes} nodes")

    times: dict = {}
    stats: dict = {}
    for _ in range(args.repeat):
        pairs = one_iteration(field, model, maps, params, times, stats)
    print(f"one Gauss-Newton iteration at the identity field, {pairs} pairs (median of {args.repeat}):")
    for name, v in times.items():
        print(f"  {name:34s} {statistics.median(v) * 1000:8.1f} ms")
    for name, v in stats.items():
        print(f"  {name:34s} {max(v):8.3g} (max)")

    solve_times, res = [], None
    for _ in range(args.solves):
        t0 = time.perf_counter()
        _, res = solve_nonrigid(field, *model, *maps, params)
        solve_times.append(time.perf_counter() - t0)
    print(f"solve_nonrigid: median {statistics.median(solve_times) * 1000:.0f} ms "
          f"(all: {', '.join(f'{t * 1000:.0f}' for t in solve_times)} ms); {res.iterations} iterations, "
          f"converged {res.converged}, {res.correspondences} pairs, rmse {res.data_rmse_m * 1000:.3f} mm")
    print("  energies " + " ".join(f"{e:.6g}" for e in res.energies))


if __name__ == "__main__":
    main()
