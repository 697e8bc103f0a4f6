"""Benchmark of `surfelwarp batch`: the same sequences on 1 and on 2 local worker processes.

    python -m surfelwarp.data_tools.bench_batch [--sequences 8] [--frames 15] [--size 320x240]

Renders `--sequences` short synthetic sequences (the scenes of data_tools.scenes in turn),
then runs `surfelwarp batch` on them with 1 worker and again (into a fresh folder) with 2, as a
user would (a new process each: its start, the cluster's and the workers' are counted).
Prints each batch's wall time, the speed-up, the sum of the tasks' own times from summary.csv,
and the overhead per task: (wall time x workers - sum of task times) / tasks, which holds the
interpreter's and cluster's start, scheduling, each worker's imports and GL context, and a
worker idle at the end. The machine may be shared: run it on an idle one.
"""
from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .scenes import SCENES
from .synth import generate


def timed_batch(inputs: list[Path], out: Path, workers: int) -> tuple[float, float]:
    """(wall seconds, sum of the tasks' own seconds)."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "surfelwarp", "batch", *map(str, inputs), "--out", str(out),
                           "--workers", str(workers), "--save-every", "100", "--no-render", "--no-progress"],
                          capture_output=True, text=True)
    wall = time.perf_counter() - start
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    if proc.returncode != 0 or any(r["status"] != "done" for r in rows):
        raise SystemExit(f"the batch did not run every sequence: {proc.stderr.strip()[-300:]}")
    return wall, sum(float(r["seconds"]) for r in rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=8)
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--size", default="320x240")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    names = [name for name in SCENES if not name.startswith("orbit")]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        inputs = [generate(names[i % len(names)], root / f"seq{i}", frames=args.frames, size=size)
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
