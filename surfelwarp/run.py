"""The frame loop shared by every method: read, preprocess, process, save."""
from __future__ import annotations

import sys
import time
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from surfelwarp.errors import InputError
from surfelwarp.io.outputs import RunOutputs
from surfelwarp.io.sequence import Sequence
from surfelwarp.methods.protocol import Method
from surfelwarp.preprocess import PreprocessParams, preprocess


def input_config(seq: Sequence, start: int, max_frames: int | None) -> dict:
    """How the input was read, for metrics.json."""
    return {"layout": seq.layout, "color": seq.has_color, "depth_scale": seq.depth_scale, "start": start,
            "max_frames": max_frames,
            "intrinsics": {k: getattr(seq.intrinsics, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}}


def run_sequence(seq: Sequence, out_dir: Path, method: Method, *, save_every: int = 10,
                 preprocess_params: PreprocessParams = PreprocessParams(), input_config: dict | None = None,
                 progress: bool | None = None) -> RunOutputs:
    """Process every frame of `seq` with `method`, writing the contract's outputs to `out_dir`.

    On bad input mid-run, metrics.json is written for the frames done so far (with an "error"
    field) and the InputError propagates.
    """
    for note in seq.notes:      # once per run, before the progress bar
        print(f"surfelwarp: note: {note}", file=sys.stderr)
    config = {"input": input_config or {}, "preprocess": asdict(preprocess_params),
              "method": method.config(), "save_every": save_every}
    outputs = RunOutputs(out_dir, method.name, seq.root, config)
    # disable=None: tqdm shows the bar only when stderr is a terminal.
    bar = tqdm(total=len(seq), unit="frame", desc=method.name, disable=None if progress is None else not progress)
    try:
        frames = seq.frames()
        for i in range(len(seq)):
            t0 = time.perf_counter()
            files, depth = next(frames)
            color = seq.read_color(files)
            t1 = time.perf_counter()
            obs = preprocess(depth, seq.intrinsics, files.index, i, preprocess_params, color)
            t2 = time.perf_counter()
            record = method.process(obs)
            t3 = time.perf_counter()
            record.seconds = {"read": t1 - t0, "preprocess": t2 - t1, **record.seconds, "total": t3 - t0}
            outputs.add_frame(record)
            if i % save_every == 0 or i == len(seq) - 1:
                outputs.save_live(files.index, *method.live_vertices())
                if i == 0:
                    outputs.remove_stale_live({f.index for j, f in enumerate(seq.files)
                                               if j % save_every == 0 or j == len(seq) - 1})
                outputs.write_metrics()
            bar.update(1)
            bar.set_postfix_str(f"surfels={record.surfels}", refresh=False)
        outputs.save_model(*method.model_vertices())
        method.finish(out_dir, outputs.frames)
    except InputError as exc:
        outputs.error = str(exc)
        raise
    finally:
        bar.close()
        if outputs.frames:   # never replace an earlier run's metrics with an empty list
            outputs.write_metrics()
    return outputs
