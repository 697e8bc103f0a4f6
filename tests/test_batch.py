"""`surfelwarp batch` on a Dask LocalCluster of 2 worker processes: done, failed and skipped
sequences, the summary, and a worker killed mid-task."""
import csv
import os
import threading
import time
from functools import partial

import pytest

pytest.importorskip("dask.distributed")
pytestmark = pytest.mark.slow      # clusters of worker processes: seconds each
from dask.distributed import Client, LocalCluster  # noqa: E402

from surfelwarp.batch import batch, unique_names  # noqa: E402
from surfelwarp.cli import batch_setup  # noqa: E402

from conftest import two_colours, write_sequence  # noqa: E402
from test_faults import run_here  # noqa: E402


def rows(out):
    with open(out / "summary.csv", newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def test_two_done_one_failed_then_two_skipped(tmp_path):
    inputs = [write_sequence(tmp_path / name, frames=range(5), color=two_colours) for name in ("a", "b")]
    broken = write_sequence(tmp_path / "broken", frames=range(5))
    (broken / "depthIntrinsics.txt").write_text("not numbers")
    out = tmp_path / "out"
    code, err = run_here("batch", *inputs, broken, "--out", out, "--workers", 2, "--save-every", 2)
    assert code == 1, err
    first = rows(out)
    assert list(first) == ["a", "b", "broken"]
    assert list(first["a"])[:6] == ["name", "input", "status", "frames", "median_frame_seconds", "message"]
    assert [first[n]["status"] for n in first] == ["done", "done", "failed"]
    assert first["a"]["frames"] == "5" and float(first["a"]["median_frame_seconds"]) > 0
    assert "depthIntrinsics.txt" in first["broken"]["message"] and "does not parse" in first["broken"]["message"]
    # each sequence's folder is what `run` writes
    for name in ("a", "b"):
        assert {"metrics.json", "model.ply", "model_mesh.ply", "live.mp4"} <= {p.name for p in (out / name).iterdir()}
    assert (out / "summary.md").read_text().count("| done |") == 2
    # again: the complete ones are skipped, the broken one fails again
    code, _ = run_here("batch", *inputs, broken, "--out", out, "--workers", 2, "--save-every", 2)
    again = rows(out)
    assert code == 1 and [again[n]["status"] for n in again] == ["skipped", "skipped", "failed"]
    # other parameters are another run: not skipped
    code, _ = run_here("batch", inputs[0], "--out", out, "--workers", 1, "--save-every", 3)
    assert code == 0 and rows(out)["a"]["status"] == "done"
    # a --no-render run is complete for a batch without renders, not for one that wants them:
    # that one runs it again (not resumed from the checkpoint at its end, which would draw nothing)
    other = tmp_path / "other"
    for flags, status in ((["--no-render"], "done"), (["--no-render"], "skipped"), ([], "done")):
        code, _ = run_here("batch", inputs[1], "--out", other, "--workers", 1, *flags)
        assert code == 0 and rows(other)["b"]["status"] == status and rows(other)["b"]["message"] != "resumed"
    assert (other / "b" / "live.mp4").is_file() and len(list((other / "b" / "render").glob("frame-*.png"))) == 2


def test_a_killed_worker_runs_its_sequence_again(tmp_path):
    long = write_sequence(tmp_path / "long", frames=range(40))
    short = write_sequence(tmp_path / "short", frames=range(4))
    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=40) as cluster, Client(cluster) as client:
        results = []
        worker = threading.Thread(target=lambda: results.extend(
            batch([long, short], out, partial(batch_setup, ["--save-every", "5"]), scheduler=cluster.scheduler_address,
                  progress=False)))
        worker.start()
        deadline = time.time() + 120
        while not (out / "long" / "live" / "frame-000010.ply").exists():
            assert time.time() < deadline and worker.is_alive()
            time.sleep(0.05)
        running = [addr for addr, keys in client.processing().items()
                   if any(str(k).startswith("surfelwarp-long-") for k in keys)]
        assert running
        client.run(os._exit, 1, workers=running, on_error="ignore")   # the worker process dies mid-task
        worker.join(timeout=300)
    assert [r.status for r in results] == ["done", "done"]
    assert results[0].message == "resumed" and results[0].frames == 40


def test_names_are_made_unique(tmp_path):
    assert unique_names([tmp_path / "x" / "seq", tmp_path / "y" / "seq", tmp_path / "z"]) == ["seq", "seq-2", "z"]
    # an input already named like a suffixed one keeps its name; the suffixes go round it
    named = unique_names([tmp_path / "x" / "seq", tmp_path / "y" / "seq", tmp_path / "seq-2", tmp_path / "w" / "seq"])
    assert named == ["seq", "seq-3", "seq-2", "seq-4"]
    assert unique_names([tmp_path / "seq-2", tmp_path / "x" / "seq", tmp_path / "y" / "seq"]) == ["seq-2", "seq", "seq-3"]


def test_bad_run_flags_end_the_batch_before_it_starts(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    code, err = run_here("batch", seq, "--out", tmp_path / "out", "--config", tmp_path / "missing.toml")
    assert code == 2 and "missing.toml" in err and not (tmp_path / "out").exists()
    # DIR inside an input would write into it: refused before anything is written
    before = sorted(p.name for p in seq.iterdir())
    code, err = run_here("batch", seq, "--out", seq / "runs")
    assert code == 2 and "inside it" in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in seq.iterdir()) == before
    import dask
    with dask.config.set({"distributed.comm.timeouts.connect": "2s"}):
        code, err = run_here("batch", seq, "--out", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:9")
    assert code == 2 and err.strip() == "surfelwarp: error: --scheduler tcp://127.0.0.1:9: cannot connect (OSError)", err


def test_ground_truth_adds_eval_figures(tmp_path):
    from surfelwarp.data_tools import synth
    seq = synth.generate("sheet", tmp_path / "sheet", frames=4, size=(160, 120))
    out = tmp_path / "out"
    code, err = run_here("batch", seq, "--out", out, "--workers", 1, "--save-every", 1, "--no-render")
    assert code == 0, err
    row = rows(out)["sheet"]
    assert row["status"] == "done" and 0 < float(row["epe_mean_m"]) < 0.02 and float(row["accuracy_median_m"]) > 0
