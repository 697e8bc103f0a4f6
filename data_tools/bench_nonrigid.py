"""Benchmark of the non-rigid Gauss-Newton solve on a rendered synthetic scene.

    python -m surfelwarp.data_tools.bench_nonrigid [--scene tube-wall] [--size 640x480] [--frame 2]

Renders frames 0..F of the scene (data_tools.synth), takes the valid pixels of frame 0 as the
model surfels (world = camera 0), samples nodes on them and solves for the warp to frame F at
its true camera pose, starting from the identity field. Prints the median time of every part of
one Gauss-Newton iteration and of whole solves, with the solve's iterations and energies. The
machine may be shared: compare medians of several repeats. Runs against older versions of the
solver too (public functions only), e.g. a copy of the package put first on PYTHONPATH.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from surfelwarp import nonrigid as nr
from surfelwarp.observation import preprocess
from surfelwarp.sequence import open_sequence
from surfelwarp.warp_field import WarpField, WarpFieldParams, skin, warp

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


def _parts_new(field, model, maps, params, times, stats):
    """The solver's own path (block pattern, factored Jacobian, PCG): one part at a time."""
    pts, nrm, knn, w = model
    ref = _components(np.reshape(pts, (-1, 3)))
    ref_n = _components(np.reshape(nrm, (-1, 3)))
    knn, w = np.asarray(knn, np.int64), np.asarray(w, np.float64)
    targets = _timed(times, "depth maps to world (once per solve)", nr._Targets, *maps)
    pattern = _timed(times, "block pattern (once per solve)", nr.BlockPattern, field.num_nodes, field.graph, knn)
    dq, b, signed, live, live_n = _timed(times, "warp (blend, points+normals)", nr._warp_state, field, ref, ref_n,
                                         knn, w)
    corr = _timed(times, "associate", nr._associate, live, live_n, targets, params)
    _, _, _, r, wr = _timed(times, "energy", nr._energy, field, corr, live, params)
    D = nr._twist_dual_quaternions(field, dq)
    H, g, diag = _timed(times, "jacobian + normal equations", nr._normal_equations_factored, field, pattern,
                        corr.index, b, signed, ref, corr.normals, D, r, wr, params.lambda_reg)
    exact = _timed(times, "solve step (direct, fallback)", nr.solve_step, H, g, params.damping)
    xi, its, _ = _timed(times, "solve step (pcg)", nr.solve_step_pcg, H, g, params.damping, params.pcg_rtol,
                        params.pcg_max_iterations, diag)
    stats.setdefault("pcg iterations", []).append(its)
    stats.setdefault("pcg step vs direct, relative", []).append(
        float(np.linalg.norm(xi - exact) / max(np.linalg.norm(exact), 1e-300)))
    _timed(times, "apply update", nr.apply_update, field, xi.reshape(-1, 6))
    return len(corr.index)


def _parts_old(field, model, maps, params, times, stats):
    """Versions before the block pattern: the public functions the solver called."""
    pts, nrm, knn, w = (np.asarray(a, np.float64) if i != 2 else np.asarray(a) for i, a in enumerate(model))
    live, live_n = _timed(times, "warp (blend, points+normals)", warp, pts, nrm, knn, w, field)
    corr = _timed(times, "associate", nr.associate, live, live_n, *maps, params)
    sub = corr.index
    r = _timed(times, "energy", nr.data_residuals, field, pts[sub], knn[sub], w[sub], corr.points, corr.normals)
    J = _timed(times, "jacobian + normal equations", nr.data_jacobian, field, pts[sub], knn[sub], w[sub],
               corr.normals)
    t0 = time.perf_counter()
    H, g = nr.normal_equations(field, J, knn[sub], r, np.ones_like(r), params.lambda_reg)
    times["jacobian + normal equations"][-1] += time.perf_counter() - t0
    xi = _timed(times, "solve step (direct, fallback)", nr.solve_step, H, g, params.damping)
    _timed(times, "apply update", nr.apply_update, field, np.asarray(xi).reshape(-1, 6))
    return len(sub)


def one_iteration(field, model, maps, params, times, stats):
    """The parts of one Gauss-Newton iteration at `field`, timed one by one."""
    parts = _parts_new if hasattr(nr, "_normal_equations_factored") else _parts_old
    return parts(field, model, maps, params, times, stats)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="tube-wall")
    ap.add_argument("--size", default="640x480", help="WxH of the rendered frames")
    ap.add_argument("--frame", type=int, default=2, help="solve from frame 0 to this frame")
    ap.add_argument("--node-radius", type=float, default=0.025, help="node spacing, m")
    ap.add_argument("--stride", type=int, default=1, help="use every n-th valid pixel of frame 0 as a surfel")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--solves", type=int, default=3, help="whole solves to time")
    ap.add_argument("--max-iterations", type=int, default=nr.NonRigidParams().max_iterations)
    ap.add_argument("--solver", choices=("pcg", "direct"), default=None, help="linear solver of whole solves")
    ap.add_argument("--pcg-rtol", type=float, default=None)
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    extra = {k: v for k, v in (("linear_solver", args.solver), ("pcg_rtol", args.pcg_rtol)) if v is not None}
    params = nr.NonRigidParams(max_iterations=args.max_iterations, **extra)

    with tempfile.TemporaryDirectory() as tmp:
        field, model, maps = build_problem(args.scene, size, args.frame, args.node_radius, args.stride, Path(tmp))
    print(f"{args.scene} {size[0]}x{size[1]}, frame 0 -> {args.frame}: {len(model[0])} surfels, "
          f"{field.num_nodes} nodes ({nr.__file__})")

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
        _, res = nr.solve_nonrigid(field, *model, *maps, params)
        solve_times.append(time.perf_counter() - t0)
    print(f"solve_nonrigid: median {statistics.median(solve_times) * 1000:.0f} ms "
          f"(all: {', '.join(f'{t * 1000:.0f}' for t in solve_times)} ms); {res.iterations} iterations, "
          f"converged {res.converged}, {res.correspondences} pairs, rmse {res.data_rmse_m * 1000:.3f} mm")
    print("  energies " + " ".join(f"{e:.6g}" for e in res.energies))


if __name__ == "__main__":
    main()
