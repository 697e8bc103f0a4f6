"""Benchmark: what the parts that hold ambiguous scenes cost per frame, inside the pipeline.

    python -m surfelwarp.data_tools.bench_ambiguity [--scene table] [--frames 15] [--size 640x480]

Renders the scene (data_tools.synth), runs SurfelWarp on it and times, per frame, each new
part where the pipeline calls it: the free-space term (building the per-layer distance
transforms and evaluating the residuals inside the Gauss-Newton solve), the carving of surfels
the camera saw through, the misalignment fractions, the coverage test before appending, and
rigid ICP's second run that holds the weak directions, and the directions each node's pairs see
for the anchors' release test. Prints the median per frame of each
and their sum against the median frame. The machine may be shared: compare ratios of one run.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from surfelwarp.io.sequence import open_sequence
from surfelwarp.methods.surfelwarp import pipeline
from surfelwarp.preprocess import preprocess
from surfelwarp.tracking import gauss_newton, rigid_icp
from surfelwarp.tracking import free_space as silhouette
from surfelwarp.tracking.terms import rest_anchors

from .synth import _size, generate


def _wrap(owner, name: str, label: str, spent: dict, keep=None):
    """Replace owner.name by a timed version that adds its seconds to spent[label] (only for
    calls where keep(args) holds, if given, and not inside another timed call, which already
    counts them); returns the restore function."""
    original = getattr(owner, name)

    def timed(*args, **kw):
        if spent["_depth"]:
            return original(*args, **kw)
        spent["_depth"] += 1
        t0 = time.perf_counter()
        try:
            return original(*args, **kw)
        finally:
            spent["_depth"] -= 1
            if keep is None or keep(args):
                spent[label] += time.perf_counter() - t0

    setattr(owner, name, timed)
    return lambda: setattr(owner, name, original)


def measure(scene: str, frames: int, size: tuple[int, int], out: Path) -> tuple[dict, list[float]]:
    """Per-frame seconds of each part, and the frames' total seconds."""
    generate(scene, out, frames=frames, size=size)
    seq = open_sequence(out)
    spent: dict = defaultdict(float)
    restore = [
        _wrap(silhouette.FreeSpace, "__init__", "free space: distance transforms", spent),
        _wrap(silhouette.FreeSpace, "residuals", "free space: residuals", spent),
        _wrap(silhouette.FreeSpace, "seen_through", "carving", spent),
        _wrap(gauss_newton, "measure", "misalignment fractions", spent),
        _wrap(pipeline, "unmatched_depth_pixels", "coverage before appending", spent),
        # The second ICP run only happens for weak directions (its ratio argument).
        _wrap(rigid_icp, "_align", "rigid ICP: weak directions held", spent,
              keep=lambda a: a[4] == rigid_icp.RigidParams().weak_eigen_ratio),
        _wrap(rigid_icp, "_median_residual", "rigid ICP: weak directions held", spent),
        _wrap(rest_anchors, "seen_directions", "release along seen directions", spent),
    ]
    per_part, totals = defaultdict(list), []
    try:
        method = pipeline.SurfelWarpMethod(seq.intrinsics)
        for i, (files, depth) in enumerate(seq.frames()):
            obs = preprocess(depth, seq.intrinsics, files.index, i)
            spent.clear()
            t0 = time.perf_counter()
            method.process(obs)
            if i > 0:
                totals.append(time.perf_counter() - t0)
                for label in ("free space: distance transforms", "free space: residuals", "carving",
                              "misalignment fractions", "coverage before appending", "rigid ICP: weak directions held",
                              "release along seen directions"):
                    per_part[label].append(spent[label])
    finally:
        for undo in restore:
            undo()
    return per_part, totals


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="table")
    parser.add_argument("--frames", type=int, default=15)
    parser.add_argument("--size", type=_size, default=(640, 480))
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        parts, totals = measure(args.scene, args.frames, args.size, Path(tmp) / args.scene)
    frame = statistics.median(totals)
    print(f"{args.scene} {args.size[0]}x{args.size[1]}, {len(totals)} frames: median frame {1000 * frame:.0f} ms")
    total = 0.0
    for label, values in parts.items():
        m = statistics.median(values)
        total += m
        print(f"  {label:<34} {1000 * m:7.1f} ms  {100 * m / frame:5.1f} %")
    print(f"  {'all new parts':<34} {1000 * total:7.1f} ms  {100 * total / frame:5.1f} %")


if __name__ == "__main__":
    main()
