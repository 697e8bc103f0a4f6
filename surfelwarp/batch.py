"""`surfelwarp batch INPUT... --out DIR`: one Dask task per sequence, on a local cluster of worker
processes or on an existing scheduler (CONTRACT.md, "Many sequences").

Each task is `surfelwarp run INPUT --out DIR/<name> [run flags]` in a worker process (one
thread a worker: the GL context of a process is not shared between threads). A task whose
outputs are complete for the same parameters is skipped; one with a checkpoint resumes. A bad
sequence fails with its one-line message and never stops the others; a worker that dies is
replaced by the nanny and its task runs again (from its checkpoint). DIR/summary.csv and
DIR/summary.md list every sequence.
"""
from __future__ import annotations

import csv
import io
import json
import time
import traceback
import uuid
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from surfelwarp.errors import InputError
from surfelwarp.io.ply import write_atomic

COLUMNS = ("name", "input", "status", "frames", "median_frame_seconds", "message")


@dataclass
class TaskResult:
    """One row of summary.csv (the contract's columns first)."""
    name: str
    input: str
    status: str                    # done, failed or skipped
    frames: int = 0
    median_frame_seconds: float = 0.0
    message: str = ""
    peak_rss_mb: float = 0.0       # of the worker process, up to the end of this task
    seconds: float = 0.0           # the task's wall time on its worker
    evaluation: dict = field(default_factory=dict)   # eval's averages, where there is ground truth


def unique_names(inputs: list[Path]) -> list[str]:
    """Each input folder's name, with -2, -3, ... where two share one. A suffix skips the names
    other inputs have (a/seq, b/seq, seq-2 -> seq, seq-3, seq-2): no two share an output folder."""
    bases = [Path(path).resolve().name or "sequence" for path in inputs]
    taken = set(bases)
    names, seen = [], set()
    for base in bases:
        name, k = base, 1
        while name in seen or (name != base and name in taken):
            k += 1
            name = f"{base}-{k}"
        seen.add(name)
        taken.add(name)
        names.append(name)
    return names


def _complete(out: Path, identity: dict, frames: int) -> dict | None:
    """metrics.json of a finished run of the same input and parameters in `out`, else None."""
    from surfelwarp.io.checkpoint import run_identity
    try:
        metrics = json.loads((out / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    # model_mesh.ply is written after model.ply and before the last metrics.json
    if not (out / "model_mesh.ply").is_file() or "error" in metrics:
        return None
    done = run_identity(metrics.get("method"), Path(metrics.get("input", "")), metrics.get("config", {}))
    summary = metrics.get("summary", {})
    finished = summary.get("frames", 0) + len(summary.get("skipped_frames", [])) == frames
    return metrics if done == identity and finished else None


def run_task(name: str, input_path: str, out: str, prepare: Callable[[str, str], dict]) -> TaskResult:
    """One sequence, on a worker: skipped if complete, resumed from a checkpoint, or run.
    prepare(input, out) gives run_sequence's arguments (the CLI's `run` flags, checked)."""
    from surfelwarp.io.checkpoint import NAME, run_identity
    from surfelwarp.io.outputs import peak_rss_mb
    from surfelwarp.run import run_config, run_sequence

    start = time.perf_counter()
    result = TaskResult(name, input_path, "failed")
    try:
        setup = prepare(input_path, out)
        seq, method = setup["seq"], setup["method"]
        config = run_config(method, setup["save_every"], setup["preprocess_params"], setup["input_config"])
        identity = run_identity(method.name, seq.root, config)
        done = _complete(Path(out), identity, len(seq))
        # A --no-render run is not complete for a batch that wants the renders.
        rendered = not setup["render"] or (Path(out) / "live.mp4").is_file()
        if done is not None and rendered:
            summary = done["summary"]
            result = TaskResult(name, input_path, "skipped", summary["frames"], summary["median_frame_seconds"],
                                "outputs complete", summary.get("peak_rss_mb", 0.0))
        else:
            # A finished run lacking only the renders keeps its checkpoint at its end: resumed,
            # it would draw nothing, so it runs again.
            resume = (Path(out) / NAME).is_file() and done is None
            try:
                outputs = run_sequence(**setup, resume=resume)
            except InputError as exc:
                if not (resume and "belongs to another run" in exc.problem):
                    raise
                outputs = run_sequence(**setup)     # a checkpoint of other parameters: start again
            summary = outputs.summary()
            result = TaskResult(name, input_path, "done", summary["frames"], summary["median_frame_seconds"],
                                "resumed" if resume else "", summary["peak_rss_mb"])
            result.evaluation = _evaluate(Path(out), seq.root)
    except InputError as exc:
        result.message = str(exc)
    except SystemExit as exc:                      # argparse rejected a flag
        result.message = f"bad run flags (exit {exc.code})"
    except Exception as exc:                       # a bug: the batch goes on, the row says where
        frame = traceback.extract_tb(exc.__traceback__)[-1]
        first_line = (str(exc).splitlines() or [""])[0]
        where = f"{Path(frame.filename).name}:{frame.lineno}"
        result.message = f"internal error {exc.__class__.__name__}: {first_line} ({where})"
    result.seconds = time.perf_counter() - start
    result.peak_rss_mb = result.peak_rss_mb or round(peak_rss_mb(), 1)
    return result


def _evaluate(out: Path, seq_root: Path) -> dict:
    """eval's averages and trajectory figures where the sequence has ground truth ({} if not)."""
    try:
        from surfelwarp.data_tools.evaluate import evaluate
    except ImportError:
        return {}
    try:
        doc = evaluate(out, seq_root)
    except InputError:
        return {}
    # In metres, as every output of a run (CONTRACT.md); eval.json itself reads in mm and cm.
    average, trajectory = doc["average"], doc.get("trajectory", {})
    figures = {"epe_mean_m": _scaled(average.get("epe_mean_mm"), 1e-3),
               "accuracy_median_m": _scaled(average.get("accuracy_median_mm"), 1e-3),
               "completeness_10mm_pct": average.get("completeness_10mm_pct"),
               "ate_m": _scaled(trajectory.get("ate_cm"), 1e-2)}
    return {k: v for k, v in figures.items() if v is not None}


def _scaled(value: float | None, scale: float) -> float | None:
    return None if value is None else value * scale


def batch(inputs: list[Path], out_dir: Path, prepare: Callable[[str, str], dict], workers: int = 2,
          scheduler: str | None = None, progress: bool | None = None) -> list[TaskResult]:
    """Every input as one task; the results in input order (summary files written)."""
    import dask
    from dask.distributed import Client, LocalCluster, as_completed

    out_dir = Path(out_dir)
    names = unique_names(inputs)
    if scheduler is None:
        # A task whose worker dies runs once more, then fails (Dask's default is 3 more).
        with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=40)
        client = Client(cluster)
    else:
        try:
            cluster, client = None, Client(scheduler)     # waits distributed.comm.timeouts.connect
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(None, f"--scheduler {scheduler}: cannot connect ({exc.__class__.__name__})") from None
    results: dict[str, TaskResult] = {}
    batch_id = uuid.uuid4().hex[:8]        # two batches on one scheduler never share a task key
    try:
        futures = {client.submit(run_task, name, str(Path(path).resolve()), str((out_dir / name).resolve()),
                                 prepare, key=f"surfelwarp-{name}-{batch_id}", pure=False): name
                   for name, path in zip(names, inputs)}
        start = time.perf_counter()
        bar = tqdm(total=len(futures), unit="sequence", desc="batch",
                   disable=None if progress is None else not progress)
        frames = 0
        for future in as_completed(futures):
            name = futures[future]
            try:
                result = future.result()
            except Exception as exc:      # the task's worker died more often than Dask retries
                result = TaskResult(name, str(inputs[names.index(name)]), "failed",
                                    message=f"worker lost: {exc.__class__.__name__}: {exc}")
            results[name] = result
            frames += result.frames if result.status == "done" else 0
            bar.update(1)
            bar.set_postfix_str(f"{frames / max(time.perf_counter() - start, 1e-9):.1f} frames/s", refresh=False)
            write_summary(out_dir, [results[n] for n in names if n in results])
        bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return [results[n] for n in names]


def write_summary(out_dir: Path, results: list[TaskResult]) -> None:
    """DIR/summary.csv (the contract's columns, then peak_rss_mb, seconds, eval figures) and summary.md."""
    extra = sorted({k for r in results for k in r.evaluation})
    header = list(COLUMNS) + ["peak_rss_mb", "seconds"] + extra
    rows = []
    for r in results:
        row = {f.name: getattr(r, f.name) for f in fields(r) if f.name != "evaluation"} | r.evaluation
        rows.append({k: _cell(row.get(k, "")) for k in header})
    text = io.StringIO()
    writer = csv.DictWriter(text, header, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(out_dir / "summary.csv", text.getvalue().encode())
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(row[k]).replace("|", "\\|") for k in header) + " |" for row in rows]
    write_atomic(out_dir / "summary.md", ("\n".join(lines) + "\n").encode())


def _cell(value):
    return round(value, 4) if isinstance(value, float) else value


