"""The comparison's PNG plots (matplotlib, Agg backend)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelwarp.report.metrics import model_counts, stage_seconds
from surfelwarp.report.renders import crop_to_content
from surfelwarp.report.runner import LABELS, METHODS


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_timing(metrics: dict[str, dict], path: Path) -> None:
    plt = _plt()
    stages: list[str] = []
    data = {}
    for name in METHODS:
        data[name] = stage_seconds(metrics[name])
        stages += [s for s in data[name][1] if s not in stages]
    colours = dict(zip(stages, plt.get_cmap("tab20").colors))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for ax, name in zip(axes, METHODS):
        frames, seconds = data[name]
        bottom = np.zeros(len(frames))
        for stage, s in seconds.items():
            ax.bar(frames, s * 1000, bottom=bottom * 1000, width=0.9, color=colours[stage], label=stage)
            bottom += s
        ax.set_title(f"{LABELS[name]}: median {np.median([f['seconds']['total'] for f in metrics[name]['frames']]) * 1000:.0f} ms/frame")
        ax.set_xlabel("frame")
        ax.legend(fontsize=7, ncol=2)
    axes[0].set_ylabel("time per frame (ms)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_model_size(metrics: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, (ax_n, ax_b) = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, style in zip(METHODS, ("-", "--")):
        frames = [f["frame"] for f in metrics[name]["frames"]]
        for key, values in model_counts(metrics[name]).items():
            ax_n.plot(frames, values, style, label=f"{LABELS[name]} {key.replace('_', ' ')}")
        mb = [f.get("model_bytes", 0) / 2 ** 20 for f in metrics[name]["frames"]]
        ax_b.plot(frames, mb, style, label=LABELS[name])
    ax_n.set_yscale("log")
    ax_n.set_ylabel("elements")
    ax_b.set_ylabel("model memory (MiB)")
    ax_b.set_yscale("log")
    for ax in (ax_n, ax_b):
        ax.set_xlabel("frame")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_memory(metrics: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    names = [LABELS[n] for n in METHODS]
    peak = [metrics[n]["summary"]["peak_rss_mb"] for n in METHODS]
    model = [max(f.get("model_bytes", 0) for f in metrics[n]["frames"]) / 2 ** 20 for n in METHODS]
    x = np.arange(len(names))
    ax.bar(x - 0.2, peak, 0.4, label="peak RSS of the run")
    ax.bar(x + 0.2, model, 0.4, label="largest model")
    ax.set_xticks(x, names)
    ax.set_ylabel("MiB")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


ACCURACY_PLOTS = (("accuracy_median_mm", "accuracy, median (mm)"),
                  ("completeness_10mm_pct", "completeness at 1 cm (%)"),
                  ("epe_mean_mm", "end-point error, mean (mm)"))


def plot_accuracy(results: dict[str, dict], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, len(ACCURACY_PLOTS), figsize=(14, 4))
    for ax, (key, label) in zip(axes, ACCURACY_PLOTS):
        for name, marker in zip(METHODS, ("o-", "s--")):
            rows = results[name]["frames"]
            ax.plot([r["frame"] for r in rows], [np.nan if r[key] is None else r[key] for r in rows],
                    marker, label=LABELS[name])
        ax.set_title(label)
        ax.set_xlabel("frame")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_topology(results: dict[str, dict], frames: np.ndarray, gap_mm: np.ndarray, phases: dict[str, list[int]],
                  path: Path) -> None:
    plt = _plt()
    panels = (("gap", "gap between the parts, ground truth (mm)"),
              ("accuracy_mean_mm", "accuracy, mean (mm)"),
              ("precision_5mm_pct", "precision at 5 mm (%)"),
              ("epe_mean_mm", "end-point error, mean (mm)"))
    fig, axes = plt.subplots(1, len(panels), figsize=(18, 4))
    contact = phases["in contact"]
    for ax, (key, label) in zip(axes, panels):
        ax.axvspan(contact[0] - 0.5, contact[-1] + 0.5, color="0.85", label="in contact")
        if key == "gap":
            ax.plot(frames, gap_mm, "k-")
        else:
            for name, marker in zip(METHODS, ("o-", "s--")):
                rows = results[name]["frames"]
                ax.plot([r["frame"] for r in rows], [np.nan if r[key] is None else r[key] for r in rows],
                        marker, label=LABELS[name])
            ax.legend(fontsize=8)
        ax.set_title(label)
        ax.set_xlabel("frame")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_normals(panels: list[tuple[str, np.ndarray]], title: str, path: Path) -> None:
    plt = _plt()
    panels = crop_to_content(panels)
    h, w = panels[0][1].shape[:2]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.2 * h / w + 0.6))
    for ax, (label, image) in zip(np.atleast_1d(axes), panels):
        ax.imshow(image)
        ax.set_title(label)
        ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
