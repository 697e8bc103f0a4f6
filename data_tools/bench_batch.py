"""Benchmark of `surfelwarp batch`: the same sequences on 1 and on 2 local worker processes.

    python -m surfelwarp.data_tools.bench_batch [--sequences 8] [--frames 15] [--size 320x240]

Renders `--sequences` short synthetic sequences (the scenes of data_tools.scenes in turn),
then runs them as one batch on a LocalCluster of 1 worker and again (into a fresh folder) on 2.
Prints each batch's wall time, the speed-up, the sum of the tasks' own times, and the overhead
per task: (wall time x workers - sum of task times) / tasks, which holds the cluster's start,
scheduling, each worker's imports and GL context, and idle workers at the end. The machine
may be shared: run it on an idle one.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from surfelwarp.batch import batch

from .scenes import SCENES
from .synth import generate


def timed_batch(inputs: list[Path], out: Path, workers: int) -> tuple[float, float]:
    """(wall seconds, sum of the tasks' own seconds)."""
    start = time.perf_counter()
    results = batch(inputs, out, ["--save-every", "100", "--no-render"], workers=workers, progress=False)
    wall = time.perf_counter() - start
    failed = [r for r in results if r.status != "done"]
    if failed:
        raise SystemExit(f"{len(failed)} sequences did not run: {failed[0].message}")
    return wall, sum(r.seconds for r in results)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=8)
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--size", default="320x240")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    names = [name for name in SCENES if name not in ("orbit", "orbit-flat", "orbit-shaded")]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        inputs = [generate(names[i % len(names)], root / f"seq{i}", frames=args.frames, size=size, progress=False)
                  for i in range(args.sequences)]
        one, tasks_one = timed_batch(inputs, root / "one", 1)
        two, tasks_two = timed_batch(inputs, root / "two", 2)
    n = args.sequences
    print(f"{n} sequences of {args.frames} frames at {args.size}")
    print(f"1 worker:  {one:6.1f} s wall, tasks {tasks_one:6.1f} s, overhead per task {(one - tasks_one) / n:5.2f} s")
    print(f"2 workers: {two:6.1f} s wall, tasks {tasks_two:6.1f} s, overhead per task "
          f"{(2 * two - tasks_two) / n:5.2f} s")
    print(f"speed-up 2 workers / 1: {one / two:.2f}x")


if __name__ == "__main__":
    main()
