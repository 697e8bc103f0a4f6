"""`surfelwarp compare INPUT --out OUT`: SurfelWarp and the DynamicFusion baseline side by side.

Both methods run on the same frames with the same preprocessing, each in a fresh process (so
each one's peak memory is its own), into OUT/surfelwarp and OUT/dynamicfusion (the outputs
of `surfelwarp run`). Then OUT/report.md is written with PNG plots: time per frame by stage,
model size over frames (surfels vs voxels, and bytes), peak memory, accuracy / completeness /
EPE where the sequence has ground truth (data_tools.evaluate), and normal-map renders of both
live models at a few frames (colour = normal, drawn with the solver-map and mesh-map renderers).
"""
from __future__ import annotations

from pathlib import Path

from surfelwarp.errors import InputError
from surfelwarp.report.contact import contact_gaps, phase_averages, phase_render_frames, topology_phases
from surfelwarp.report.document import write_report
from surfelwarp.report.metrics import evaluate_runs, load_metrics
from surfelwarp.report.plots import (_plt, plot_accuracy, plot_memory, plot_model_size, plot_normals, plot_timing,
                                     plot_topology)
from surfelwarp.report.renders import input_normals, pick_frames, render_live
from surfelwarp.report.runner import LABELS, METHODS, CompareSpec, open_input, run_in_child


def compare(spec: CompareSpec, render_frames: list[int] | None = None) -> Path:
    """Run both methods, evaluate, plot; returns the path of report.md."""
    out = Path(spec.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    seq = open_input(spec)                      # bad input fails here, before any run
    try:
        _plt()
    except ImportError:
        raise InputError(None, "compare draws its plots with matplotlib: pip install matplotlib") from None
    for name in METHODS:
        run_in_child(name, spec)
    metrics = {name: load_metrics(out / name) for name in METHODS}
    results = evaluate_runs(out, spec.input)
    plot_timing(metrics, out / "timing.png")
    plot_model_size(metrics, out / "model_size.png")
    plot_memory(metrics, out / "memory.png")
    topology = None
    if results is not None:
        plot_accuracy(results, out / "accuracy.png")
        gaps = contact_gaps(spec.input)
        phases = None if gaps is None else topology_phases(*gaps)
        if phases is not None:
            topology = (phases, phase_averages(results, phases))
            plot_topology(results, *gaps, phases, out / "topology.png")
            if render_frames is None:
                render_frames = phase_render_frames(out, phases)
    images = []
    for frame in (pick_frames(out) if render_frames is None else render_frames):
        panels = []
        observed = input_normals(seq, frame, spec.preprocess)
        if observed is not None:
            panels.append(("input depth", observed))
        for name in METHODS:
            ply = out / name / "live" / f"frame-{frame:06d}.ply"
            if ply.exists():
                panels.append((LABELS[name], render_live(ply, seq.intrinsics)))
        if len(panels) > (observed is not None):
            file = f"normals-{frame:06d}.png"
            plot_normals(panels, f"frame {frame}", out / file)
            images.append((frame, file))
    return write_report(out, spec, seq, metrics, results, images, topology)
