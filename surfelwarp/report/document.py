"""OUT/report.md: the tables and the text around the plots."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelwarp.report.contact import CONTACT_MM, PHASE_KEYS
from surfelwarp.report.metrics import speed, stage_seconds
from surfelwarp.report.runner import LABELS, METHODS, CompareSpec


def surfelwarp_variant(metrics: dict) -> str:
    """Which SurfelWarp ran, from its metrics.json config."""
    fusion = metrics.get("config", {}).get("method", {}).get("fusion_enabled")
    if fusion is False:
        return ("template tracking (`fusion=False`: the first frame's surfels tracked, never fused, "
                "extended or reinitialised)")
    if fusion is True:
        return "the full pipeline with surfel fusion (`fusion=True`)"
    return "an unknown variant (its metrics.json has no boolean `fusion_enabled`)"


def _fmt(value, digits=1) -> str:
    return "-" if value is None or (isinstance(value, float) and not np.isfinite(value)) else f"{value:.{digits}f}"


def summary_rows(metrics: dict[str, dict], results: dict[str, dict] | None) -> list[tuple[str, ...]]:
    rows = []

    def row(label, fn, digits=1):
        rows.append((label, *(_fmt(fn(n), digits) for n in METHODS)))

    def median_stage(name, stage):
        values = [f["seconds"][stage] for f in metrics[name]["frames"][1:] if stage in f["seconds"]]
        return 1000 * float(np.median(values)) if values else None

    row("frames", lambda n: metrics[n]["summary"]["frames"], 0)
    row("first frame (ms)", lambda n: 1000 * metrics[n]["frames"][0]["seconds"]["total"], 0)
    row("median time per frame (ms)", lambda n: 1000 * metrics[n]["summary"]["median_frame_seconds"], 0)
    stages = []
    for n in METHODS:
        stages += [s for s in stage_seconds(metrics[n])[1]
                   if s not in stages and any(s in f["seconds"] for f in metrics[n]["frames"][1:])]
    for stage in stages:
        row(f"  {stage} (ms, median after frame 1)", lambda n, s=stage: median_stage(n, s), 1)
    last = {n: metrics[n]["frames"][-1] for n in METHODS}
    row("surfels (last frame)", lambda n: last[n].get("surfels") or None, 0)
    row("voxels (last frame)", lambda n: last[n].get("voxels"), 0)
    row("mesh vertices (last frame)", lambda n: last[n].get("mesh_vertices"), 0)
    row("nodes (last frame)", lambda n: last[n].get("nodes"), 0)
    row("model memory, last frame (MiB)", lambda n: last[n].get("model_bytes", 0) / 2 ** 20, 1)
    row("peak RSS (MiB)", lambda n: metrics[n]["summary"]["peak_rss_mb"], 0)
    if results:
        avg = {n: results[n]["average"] for n in METHODS}
        row("accuracy, median (mm)", lambda n: avg[n].get("accuracy_median_mm"), 2)
        row("completeness at 5 mm (%)", lambda n: avg[n].get("completeness_5mm_pct"), 1)
        row("completeness at 1 cm (%)", lambda n: avg[n].get("completeness_10mm_pct"), 1)
        row("F-score at 5 mm (%)", lambda n: avg[n].get("fscore_5mm_pct"), 1)
        row("normal consistency", lambda n: avg[n].get("normal_consistency"), 3)
        row("EPE, mean (mm)", lambda n: avg[n].get("epe_mean_mm"), 1)
        row("EPE under 2 cm (%)", lambda n: avg[n].get("epe_under_2cm_pct"), 1)
        row("ATE (cm)", lambda n: results[n]["trajectory"].get("ate_cm"), 2)
    return rows


SPEED_TARGET = 2.0         # SurfelWarp should be at least this much faster per frame,
MODEL_SPEED_TARGET = 5.0   # and this much in the model update (issue 18)


def speed_lines(metrics: dict[str, dict]) -> list[str]:
    sp = speed(metrics)
    sw, df = sp["surfelwarp"], sp["dynamicfusion"]

    def row(label, key):
        ratio = df[key] / sw[key] if sw[key] > 0 else float("nan")
        return f"| {label} | {sw[key]:.0f} | {df[key]:.0f} | {ratio:.2f}x |"

    lines = ["## Speed", "",
             f"SurfelWarp ran as {surfelwarp_variant(metrics['surfelwarp'])}.", "",
             f"**Speed ratio: SurfelWarp is {sp['ratio']:.2f}x faster per frame than DynamicFusion, "
             f"{sp['model_ratio']:.2f}x in the model update** (median time per frame after the first: SurfelWarp "
             f"{sw['total']:.0f} ms, DynamicFusion {df['total']:.0f} ms; targets at least {SPEED_TARGET:g}x and "
             f"{MODEL_SPEED_TARGET:g}x).", "",
             "| median ms per frame | SurfelWarp | DynamicFusion | DynamicFusion / SurfelWarp |", "|---|---:|---:|---:|",
             row("input (read, preprocess)", "input"),
             row("tracking (solver maps, rigid ICP, data points, non-rigid GN)", "tracker"),
             row("model update (all other stages but the outputs)", "model"),
             row("total", "total"), ""]
    if sp["ratio"] < SPEED_TARGET:
        lines += [f"Below {SPEED_TARGET:g}x: SurfelWarp's frame is mostly input and tracking, which both methods "
                  f"share ({sw['input'] + sw['tracker']:.0f} of {sw['total']:.0f} ms), so even a free model update "
                  f"would make it at most {sp['ratio_bound']:.2f}x faster than DynamicFusion here; DynamicFusion's "
                  f"volumetric stages add {df['model']:.0f} ms.", ""]
    return lines


def topology_lines(phases: dict[str, list[int]], averages: dict[str, dict[str, dict]]) -> list[str]:
    contact = phases["in contact"]
    after = phases["after separation"]
    lines = ["## Topology change", "",
             f"In the ground truth the moving parts touch (gap under {CONTACT_MM:g} mm) in frames "
             f"{contact[0]}-{contact[-1]} and are apart again in frames {after[0]}-{after[-1]}. "
             "Averages over the evaluated (saved) frames of each phase:", ""]
    names = [p for p in phases if phases[p]]
    lines += ["| | " + " | ".join(f"{p}: {LABELS[n]}" for p in names for n in METHODS) + " |",
              "|---|" + "---:|" * (len(names) * len(METHODS)),
              "| evaluated frames | " + " | ".join(
                  ",".join(str(f) for f in averages[p][n]["frames"]) or "-" for p in names for n in METHODS) + " |"]
    for key, label, digits in PHASE_KEYS:
        lines.append(f"| {label} | " + " | ".join(_fmt(averages[p][n][key], digits) for p in names for n in METHODS) + " |")
    sw, df = averages["after separation"]["surfelwarp"], averages["after separation"]["dynamicfusion"]
    if df["accuracy_mean_mm"] is not None and sw["accuracy_mean_mm"] is not None:
        lines += ["", f"After separation: DynamicFusion's live surface lies {_fmt(df['accuracy_mean_mm'], 2)} mm from "
                      f"the true one on average ({_fmt(df['precision_5mm_pct'])} % of it within 5 mm), SurfelWarp's "
                      f"{_fmt(sw['accuracy_mean_mm'], 2)} mm ({_fmt(sw['precision_5mm_pct'])} %)."]
    lines += ["", "![topology change](topology.png)", ""]
    return lines


def write_report(out: Path, spec: CompareSpec, seq, metrics: dict[str, dict], results: dict[str, dict] | None,
                 normal_images: list[tuple[int, str]], topology: tuple[dict, dict] | None = None) -> Path:
    intr = seq.intrinsics
    lines = ["# SurfelWarp vs DynamicFusion", "",
             f"Input `{spec.input}` ({seq.layout}, {intr.width}x{intr.height}), "
             f"{metrics['surfelwarp']['summary']['frames']} frames from frame {seq.files[0].index}. "
             "Both methods share the rigid ICP and the non-rigid Gauss-Newton tracker; each ran alone in "
             "its own process, one after the other. Outputs: `surfelwarp/`, `dynamicfusion/` (as `surfelwarp run`).", ""]
    fields_used = {n: metrics[n].get("config", {}).get("method", {}).get("warp_field") for n in METHODS}
    if all(fields_used.values()):
        describe = lambda w: (f"nodes {1000 * w['node_radius_m']:.0f} mm apart, {w['k_skin']} skinning and "  # noqa: E731
                              f"{w['graph_k']} regularisation neighbours")
        if fields_used["surfelwarp"] == fields_used["dynamicfusion"]:
            lines += [f"Warp field of both: {describe(fields_used['surfelwarp'])}.", ""]
        else:
            lines += [f"Warp field: SurfelWarp {describe(fields_used['surfelwarp'])}; DynamicFusion "
                      f"{describe(fields_used['dynamicfusion'])}.", ""]
    lines += speed_lines(metrics)
    lines += ["## Summary", "", "| | SurfelWarp | DynamicFusion |", "|---|---:|---:|"]
    lines += [f"| {r[0]} | {r[1]} | {r[2]} |" for r in summary_rows(metrics, results)]
    if results is None:
        lines += ["", "The sequence has no ground truth: no accuracy figures."]
    else:
        lines += ["", "Accuracy, completeness and EPE: averages over the saved live frames "
                      "(`surfelwarp eval`, written to each run's `eval.json`)."]
    lines.append("")
    if topology is not None:
        lines += topology_lines(*topology)
    lines += ["## Time per frame by stage", "", "![time per frame](timing.png)", "",
              "## Model size", "", "![model size](model_size.png)", "",
              "## Memory", "", "![memory](memory.png)", ""]
    if results is not None:
        lines += ["## Accuracy against ground truth", "", "![accuracy](accuracy.png)", ""]
    if normal_images:
        lines += ["## Live models (colour = normal)", ""]
        lines += [f"Frame {frame}:\n\n![normals at frame {frame}]({name})\n" for frame, name in normal_images]
    path = out / "report.md"
    from surfelwarp.io.ply import write_atomic
    write_atomic(path, ("\n".join(lines) + "\n").encode())
    return path
