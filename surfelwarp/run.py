"""The frame loop shared by every method: read, preprocess, process, save, checkpoint."""
from __future__ import annotations

import ctypes
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from surfelwarp.errors import InputError
from surfelwarp.geometry.surfel_mesh import mesh_of
from surfelwarp.io import checkpoint
from surfelwarp.io.outputs import RunOutputs, rss_mb
from surfelwarp.io.sequence import FrameFiles, Sequence
from surfelwarp.methods.protocol import Method
from surfelwarp.preprocess import CameraObservation, PreprocessParams, preprocess
from surfelwarp.render.views import frame_panel, live_view


def input_config(seq: Sequence, start: int, max_frames: int | None) -> dict:
    """How the input was read, for metrics.json."""
    return {"layout": seq.layout, "color": seq.has_color, "depth_scale": seq.depth_scale, "start": start,
            "max_frames": max_frames,
            "intrinsics": {k: getattr(seq.intrinsics, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}}


def run_config(method: Method, save_every: int, preprocess_params: PreprocessParams, input_config: dict | None
               ) -> dict:
    """metrics.json's "config": everything in force."""
    return {"input": input_config or {}, "preprocess": asdict(preprocess_params), "method": method.config(),
            "save_every": save_every}


def _saves(position: int, count: int, save_every: int) -> bool:
    """Whether the frame at `position` of `count` is saved (the first processed one is, too)."""
    return position % save_every == 0 or position == count - 1


def _resume(out_dir: Path, identity: dict, seq: Sequence, save_every: int, outputs: RunOutputs
            ) -> tuple[Method, int]:
    """The checkpointed method and the position of its next frame; outputs take its records."""
    state = checkpoint.load(out_dir, identity)
    if state.next_position > len(seq):
        raise InputError(out_dir / checkpoint.NAME, f"checkpoint is {state.next_position} frames into the run, "
                                                    f"more than the {len(seq)} asked for")
    outputs.frames, outputs.skipped = state.frames, state.skipped
    # A run cut short by --max-frames saved its last frame; a whole run would not have.
    outputs.remove_saved({r.frame for r in outputs.frames[1:]} -
                         {f.index for j, f in enumerate(seq.files) if _saves(j, len(seq), save_every)})
    return state.method, state.next_position


def _save_frame(outputs: RunOutputs, method: Method, seq: Sequence, frame: int, depth: np.ndarray,
                color: np.ndarray | None, record, render: bool) -> None:
    """The live PLY and, with `render`, the frame's picture (timed as `render`)."""
    live = method.live_vertices()
    outputs.save_live(frame, *live)
    if render:
        t = time.perf_counter()
        if color is None and seq.has_color:      # the run's pictures keep one size
            color = np.zeros(depth.shape + (3,), np.uint8)
        outputs.save_render(frame, frame_panel(live_view(*live, seq.intrinsics), depth, color))
        record.seconds["render"] = time.perf_counter() - t


def _finish(outputs: RunOutputs, method: Method, render: bool) -> None:
    """model.ply, model_mesh.ply (the method's own faces, or the surfels meshed), live.mp4."""
    model = method.model_vertices()
    outputs.save_model(*model)
    mesh = mesh_of(*model)
    outputs.save_mesh(mesh.vertices, mesh.normals, mesh.faces, mesh.colors)
    if render:
        outputs.write_video([r.frame for r in outputs.frames])
    method.finish(outputs.out_dir, outputs.frames)


def _lowest_priority() -> None:
    """The calling thread at the lowest CPU priority (Linux, where a thread has its own nice
    value; elsewhere nothing): it gets a core the frame leaves idle, not time from the frame's
    own threads (at normal priority, detection on the worker slowed the frame's own matching on
    twist-limb by half: match_frames 81 -> 120 ms)."""
    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except OSError:
            pass


KEEP_FREED_BYTES = 1 << 30
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3      # glibc's mallopt parameters


def keep_freed_memory() -> bool:
    """Have the C library's malloc keep freed blocks of up to 1 GiB for reuse instead of
    returning them to the kernel (glibc; elsewhere, or where the user set MALLOC_* or
    GLIBC_TUNABLES, nothing); whether it took. A frame allocates and frees tens of MB of arrays
    in blocks glibc maps afresh and unmaps on free, so every page of them faulted again at its
    first write: on 7-Scenes 16-18k minor faults a frame, 45-60 ms of system time (the solver
    maps' gather alone 4.8 -> 1.3 ms a call). The process keeps its peak heap instead."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(k.startswith("MALLOC_") for k in os.environ) or "malloc" in tunables:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, KEEP_FREED_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, KEEP_FREED_BYTES))


def _read_ahead(seq: Sequence, first: int, params: PreprocessParams, method: Method
                ) -> Iterator[tuple[int, FrameFiles, np.ndarray, np.ndarray | None, CameraObservation, dict, dict]]:
    """The frames from `first`: (position, files, depth, colour, observation, the seconds the frame
    waited for them by stage, the seconds they took by stage). Each is read, preprocessed and
    given to method.ahead on one worker while the frame before it is processed: a frame is
    mostly single-threaded numpy, and the worker takes the other core. The wait is the tail of
    the worker's job: its last stages first."""
    def job(position: int, files: FrameFiles):
        t0 = time.perf_counter()
        depth, color = seq.read_depth(files), seq.read_color(files)
        t1 = time.perf_counter()
        obs = preprocess(depth, seq.intrinsics, files.index, position, params, color)
        t2 = time.perf_counter()
        method.ahead(obs)
        return depth, color, obs, {"read": t1 - t0, "preprocess": t2 - t1, "ahead": time.perf_counter() - t2}

    todo = list(enumerate(seq.files[first:], start=first))
    pool = ThreadPoolExecutor(1, thread_name_prefix="read-ahead", initializer=_lowest_priority)
    try:
        t0 = time.perf_counter()
        coming = pool.submit(job, *todo[0]) if todo else None
        for k, (position, files) in enumerate(todo):
            depth, color, obs, took = coming.result()
            left = time.perf_counter() - t0
            coming = pool.submit(job, *todo[k + 1]) if k + 1 < len(todo) else None
            waited = {}
            for stage in ("ahead", "preprocess", "read"):
                waited[stage] = min(left, took[stage])
                left -= waited[stage]
            waited["read"] += left                       # the hand-over itself
            yield position, files, depth, color, obs, {s: waited[s] for s in took}, took
            t0 = time.perf_counter()                     # the next frame's turn
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def run_sequence(seq: Sequence, out_dir: Path, method: Method, *, save_every: int = 10,
                 preprocess_params: PreprocessParams = PreprocessParams(), input_config: dict | None = None,
                 progress: bool | None = None, resume: bool = False, render: bool = True) -> RunOutputs:
    """Process every frame of `seq` with `method`, writing the contract's outputs to `out_dir`.

    With every saved frame: its live PLY (and with `render` its picture, render/frame-%06d.png),
    the checkpoint, metrics.json, in that order (a run killed between two of them resumes from a
    checkpoint no older than its metrics). At the end: model.ply, model_mesh.ply and with
    `render` live.mp4 of the saved frames' pictures. `resume`:
    go on from out_dir's checkpoint (its method replaces `method`). On bad input mid-run,
    metrics.json is written for the frames done so far (with an "error" field) and the
    InputError propagates.
    """
    keep_freed_memory()
    for note in seq.notes:      # once per run, before the progress bar
        print(f"surfelwarp: note: {note}", file=sys.stderr)
    config = run_config(method, save_every, preprocess_params, input_config)
    outputs = RunOutputs(out_dir, method.name, seq.root, config)
    outputs.missing = seq.missing
    identity = checkpoint.run_identity(method.name, seq.root, config)
    method, first = _resume(out_dir, identity, seq, save_every, outputs) if resume else (method, 0)
    claimed = resume
    # disable=None: tqdm shows the bar only when stderr is a terminal.
    bar = tqdm(total=len(seq), initial=first, unit="frame", desc=method.name,
               disable=None if progress is None else not progress)
    frames = _read_ahead(seq, first, preprocess_params, method)
    try:
        for i, files, depth, color, obs, waited, took in frames:
            t0 = time.perf_counter() - sum(waited.values())
            enough = obs.num_valid >= preprocess_params.min_valid_pixels
            if enough or method.started:
                record = method.process(obs) if enough else method.hold(obs)
            if not method.started:       # too little depth, or too little for this method to start from
                outputs.skipped.append(files.index)
                bar.update(1)
                continue
            t3 = time.perf_counter()
            if not claimed:              # this run is under way: the earlier one's outputs go
                outputs.claim()
                claimed = True
            record.seconds = {**waited, **record.seconds, "total": t3 - t0}     # read, preprocess, ahead first
            record.ahead_seconds = took
            record.rss_mb = round(rss_mb(), 1)
            outputs.add_frame(record)
            if _saves(i, len(seq), save_every) or len(outputs.frames) == 1:
                # `total` is the whole frame's wall time (CONTRACT.md), its outputs included: the
                # live PLY (`write`) and its picture (`render`). Not the checkpoint and metrics.json
                # after them, the run's bookkeeping: the checkpoint holds the frame's record.
                t4 = time.perf_counter()
                _save_frame(outputs, method, seq, files.index, depth, color, record, render)
                t5 = time.perf_counter()
                record.seconds["write"] = t5 - t4 - record.seconds.get("render", 0.0)
                record.seconds["total"] += t5 - t4
                checkpoint.save(out_dir, checkpoint.Checkpoint(identity, i + 1, method, outputs.frames,
                                                               outputs.skipped))
                outputs.write_metrics()
            bar.update(1)
            bar.set_postfix_str(f"surfels={record.surfels}", refresh=False)
        if not method.started:
            raise InputError(seq.root, f"no frame has enough valid depth to start a model "
                                       f"({len(outputs.skipped)} skipped); nothing was written")
        _finish(outputs, method, render)
    except InputError as exc:
        outputs.error = str(exc)
        raise
    finally:
        frames.close()                   # the worker stops (after the frame it is reading)
        bar.close()
        if outputs.frames and claimed:   # never replace an earlier run's metrics
            try:
                outputs.write_metrics()
            except InputError:
                pass                     # the error that ended the run is the one to report
    return outputs
