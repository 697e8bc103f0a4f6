"""The frame loop shared by every method: read, preprocess, process, save, checkpoint."""
from __future__ import annotations

import sys
import time
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from surfelwarp.errors import InputError
from surfelwarp.io import checkpoint
from surfelwarp.io.outputs import RunOutputs, rss_mb
from surfelwarp.io.sequence import Sequence
from surfelwarp.methods.protocol import Method
from surfelwarp.preprocess import PreprocessParams, preprocess


def input_config(seq: Sequence, start: int, max_frames: int | None) -> dict:
    """How the input was read, for metrics.json."""
    return {"layout": seq.layout, "color": seq.has_color, "depth_scale": seq.depth_scale, "start": start,
            "max_frames": max_frames,
            "intrinsics": {k: getattr(seq.intrinsics, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}}


def _saves(position: int, count: int, save_every: int) -> bool:
    """Whether the frame at `position` of `count` is saved (the first processed one is, too)."""
    return position % save_every == 0 or position == count - 1


def run_sequence(seq: Sequence, out_dir: Path, method: Method, *, save_every: int = 10,
                 preprocess_params: PreprocessParams = PreprocessParams(), input_config: dict | None = None,
                 progress: bool | None = None, resume: bool = False) -> RunOutputs:
    """Process every frame of `seq` with `method`, writing the contract's outputs to `out_dir`.

    With every saved frame: its live PLY, the checkpoint, metrics.json, in that order (a run
    killed between two of them resumes from a checkpoint no older than its metrics). `resume`:
    go on from out_dir's checkpoint (its method replaces `method`). On bad input mid-run,
    metrics.json is written for the frames done so far (with an "error" field) and the
    InputError propagates.
    """
    for note in seq.notes:      # once per run, before the progress bar
        print(f"surfelwarp: note: {note}", file=sys.stderr)
    config = {"input": input_config or {}, "preprocess": asdict(preprocess_params),
              "method": method.config(), "save_every": save_every}
    outputs = RunOutputs(out_dir, method.name, seq.root, config)
    outputs.missing = seq.missing
    identity = checkpoint.run_identity(method.name, seq.root, config)
    first = 0
    if resume:
        state = checkpoint.load(out_dir, identity)
        method, first = state.method, state.next_position
        if first > len(seq):
            raise InputError(out_dir / checkpoint.NAME, f"checkpoint is {first} frames into the run, more than "
                                                        f"the {len(seq)} asked for")
        outputs.frames, outputs.skipped = state.frames, state.skipped
        # A run cut short by --max-frames saved its last frame; a whole run would not have.
        outputs.remove_live({r.frame for r in outputs.frames[1:]} -
                            {f.index for j, f in enumerate(seq.files) if _saves(j, len(seq), save_every)})
    claimed = resume
    # disable=None: tqdm shows the bar only when stderr is a terminal.
    bar = tqdm(total=len(seq), initial=first, unit="frame", desc=method.name,
               disable=None if progress is None else not progress)
    try:
        for i, files in enumerate(seq.files[first:], start=first):
            t0 = time.perf_counter()
            depth, color = seq.read_depth(files), seq.read_color(files)
            t1 = time.perf_counter()
            obs = preprocess(depth, seq.intrinsics, files.index, i, preprocess_params, color)
            t2 = time.perf_counter()
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
            record.seconds = {"read": t1 - t0, "preprocess": t2 - t1, **record.seconds, "total": t3 - t0}
            record.rss_mb = round(rss_mb(), 1)
            outputs.add_frame(record)
            if _saves(i, len(seq), save_every) or len(outputs.frames) == 1:
                outputs.save_live(files.index, *method.live_vertices())
                checkpoint.save(out_dir, checkpoint.Checkpoint(identity, i + 1, method, outputs.frames,
                                                               outputs.skipped))
                outputs.write_metrics()
            bar.update(1)
            bar.set_postfix_str(f"surfels={record.surfels}", refresh=False)
        if not method.started:
            raise InputError(seq.root, f"no frame has enough valid depth to start a model "
                                       f"({len(outputs.skipped)} skipped); nothing was written")
        outputs.save_model(*method.model_vertices())
        method.finish(out_dir, outputs.frames)
    except InputError as exc:
        outputs.error = str(exc)
        raise
    finally:
        bar.close()
        if outputs.frames and claimed:   # never replace an earlier run's metrics
            try:
                outputs.write_metrics()
            except InputError:
                pass                     # the error that ended the run is the one to report
    return outputs
