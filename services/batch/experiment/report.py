"""What `topseg experiment` writes: OUT/<name>.md (our numbers beside the paper's), .json and
.png (mAP and mAR panels like the paper's Fig. 4, its curves dashed; Table I as bars)."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write
from topseg.services.batch.experiment import paper_results
from topseg.services.batch.experiment.runs import write_json

X_LABELS = {
    "noise": "training noise sigma (mm)",
    "features": "features per tree PC",
    "frames": "training frames per tree F",
    "overlap": "theta' (% overlap)",
}
COLOURS = {
    "gaussian": "tab:blue",
    "linear": "tab:blue",
    "axis": "tab:red",
    "modeled": "tab:blue",
    "non-modeled": "tab:red",
}


def _f(x) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def summary_line(doc: dict) -> str:
    """One line about a finished point: its scores beside the paper's."""
    c, f = doc["crf"], doc["forest"]
    paper = _paper_pair(doc["experiment"], doc["curve"], doc["x"])
    tail = f"; paper mAP {_f(paper[0])} mAR {_f(paper[1])}" if paper != (None, None) else ""
    return (
        f"  done {doc['experiment']} {doc['key']}: CRF ({doc['crf_mode']}) mAP {_f(c['mAP'])} "
        f"mAR {_f(c['mAR'])} avg F1 {_f(c['avg_f1'])} | forest mAP {_f(f['mAP'])} "
        f"mAR {_f(f['mAR'])} avg F1 {_f(f['avg_f1'])}{tail} "
        f"({doc['seconds']['data_and_train']:.0f} s data+train, {doc['seconds']['score']:.0f} s score)"
    )


def _paper_pair(experiment: str, curve: str, x) -> tuple[float | None, float | None]:
    if x is None:
        return None, None
    return tuple(paper_results.paper_value(experiment, m, curve, x) for m in ("mAP", "mAR"))


def write_all(out: Path, name: str, scale, crf_mode: str, test_frames: int, points, done: dict):
    """Rewrite OUT/<name>.json, .md and .png from the finished points `done` (key -> doc)."""
    doc = {
        "experiment": name,
        "scale": scale.name,
        "scale_parameters": scale.describe(),
        "crf": crf_mode,
        "test_frames": test_frames,
        "finished": len(done),
        "points_total": len(points),
        "points": [_row(name, done[p.key]) for p in points if p.key in done],
        "missing": [p.key for p in points if p.key not in done],
    }
    if name == "table":
        doc["paper_table_I"] = paper_results.TABLE_I
    else:
        doc["paper_fig4"] = paper_results.CURVES[name]
    paths = [out / f"{name}.json", out / f"{name}.md", out / f"{name}.png"]
    write_json(paths[0], doc)
    _write_text(paths[1], table_markdown(doc) if name == "table" else curve_markdown(doc))
    if name == "table":
        table_figure(doc, paths[2])
    else:
        curve_figure(doc, paths[2])
    return paths


def _row(name: str, d: dict) -> dict:
    paper = _paper_pair(name, d["curve"], d["x"])
    return {
        "curve": d["curve"],
        "x": d["x"],
        "key": d["key"],
        "mAP": d["crf"]["mAP"],
        "mAR": d["crf"]["mAR"],
        "avg_f1": d["crf"]["avg_f1"],
        "forest": {k: d["forest"][k] for k in ("mAP", "mAR", "avg_f1")},
        "paper": {"mAP": paper[0], "mAR": paper[1]},
        "per_class_f1": {
            "crf": {k: v["f1"] for k, v in d["crf"]["per_class"].items()},
            "forest": {k: v["f1"] for k, v in d["forest"]["per_class"].items()},
        },
        "seconds": d["seconds"],
        "ms_per_frame": d["ms_per_frame"],
    }


def _header(doc: dict) -> list[str]:
    lines = [
        f"# topseg experiment {doc['experiment']} ({doc['scale']} scale)",
        "",
        f"{doc['scale_parameters']}. Scores: means over the ten classes on "
        f"{doc['test_frames']} held-out frames, forest + CRF ({doc['crf']}) and the forest "
        "alone. Paper: 65 real Kinect frames.",
        "",
        f"Finished points: {doc['finished']} of {doc['points_total']}"
        + (f" (missing: {', '.join(doc['missing'])})" if doc["missing"] else ""),
        "",
    ]
    return lines


def curve_markdown(doc: dict) -> str:
    """The Markdown report of a Fig. 4 experiment: one row per point, ours beside the paper's."""
    xl = X_LABELS[doc["experiment"]]
    lines = _header(doc)
    lines += [
        f"| curve | {xl} | mAP | mAR | avg F1 | paper mAP | paper mAR | forest mAP | forest mAR "
        "| forest avg F1 | train s |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for r in sorted(doc["points"], key=lambda r: (r["curve"], r["x"])):
        lines.append(
            f"| {r['curve']} | {r['x']:g} | {_f(r['mAP'])} | {_f(r['mAR'])} | {_f(r['avg_f1'])} "
            f"| {_f(r['paper']['mAP'])} | {_f(r['paper']['mAR'])} | {_f(r['forest']['mAP'])} "
            f"| {_f(r['forest']['mAR'])} | {_f(r['forest']['avg_f1'])} "
            f"| {r['seconds']['data_and_train']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def table_markdown(doc: dict) -> str:
    """The Markdown report of Table I: per-class F1, ours beside the paper's."""
    rows = {r["curve"]: r for r in doc["points"]}
    cols = []  # (title, values: class -> f1)
    for mode in ("modeled", "non-modeled"):
        if mode in rows:
            pc = rows[mode]["per_class_f1"]
            cols.append((f"forest {mode}", {"avg": rows[mode]["forest"]["avg_f1"], **pc["forest"]}))
            cols.append((f"CRF {mode}", {"avg": rows[mode]["avg_f1"], **pc["crf"]}))
        cols.append((f"paper CRF {mode}", paper_results.TABLE_I[mode]))
    lines = _header(doc)
    lines.append("| F1 | " + " | ".join(t for t, _ in cols) + " |")
    lines.append("|---|" + "--:|" * len(cols))
    for cls in ("avg", *paper_results.TABLE_CLASSES):
        lines.append(f"| {cls} | " + " | ".join(_f(v.get(cls)) for _, v in cols) + " |")
    return "\n".join(lines) + "\n"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def curve_figure(doc: dict, path: Path) -> None:
    """mAP and mAR against the swept value; ours solid, the paper's dashed."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=90)
    curves = sorted({r["curve"] for r in doc["points"]} | set(_paper_curves(doc)))
    for ax, metric in zip(axes, ("mAP", "mAR"), strict=True):
        for curve in curves:
            colour = COLOURS.get(curve, None)
            ours = sorted((r["x"], r[metric]) for r in doc["points"] if r["curve"] == curve)
            ours = [(x, v) for x, v in ours if v is not None]
            if ours:
                ax.plot(*zip(*ours, strict=True), "o-", color=colour, label=f"topseg {curve}")
            paper = doc["paper_fig4"].get(metric, {}).get(curve)
            if paper:
                ax.plot(*zip(*paper, strict=True), "x--", color=colour, label=f"paper {curve}")
        ax.set_xlabel(X_LABELS[doc["experiment"]])
        ax.set_ylabel(f"{metric} (CRF {doc['crf']})" if doc["crf"] != "none" else metric)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"{doc['experiment']} ({doc['scale']} scale; paper dashed, real test frames)", fontsize=10
    )
    fig.tight_layout()
    _save(fig, path, plt)


def _paper_curves(doc: dict) -> set[str]:
    return {c for m in doc["paper_fig4"].values() for c in m}


def table_figure(doc: dict, path: Path) -> None:
    """Per-class F1 bars: forest and CRF, modeled and non-modeled, beside the paper's Table I."""
    plt = _plt()
    rows = {r["curve"]: r for r in doc["points"]}
    classes = ("avg", *paper_results.TABLE_CLASSES)
    series = []
    for mode, colour in (("modeled", "tab:blue"), ("non-modeled", "tab:red")):
        if mode in rows:
            r = rows[mode]
            series.append(
                (
                    f"forest {mode}",
                    {"avg": r["forest"]["avg_f1"], **r["per_class_f1"]["forest"]},
                    colour,
                    0.35,
                )
            )
            series.append(
                (f"CRF {mode}", {"avg": r["avg_f1"], **r["per_class_f1"]["crf"]}, colour, 0.8)
            )
        series.append((f"paper CRF {mode}", paper_results.TABLE_I[mode], colour, None))
    fig, ax = plt.subplots(figsize=(12, 4.5), dpi=90)
    width = 0.8 / len(series)
    x = np.arange(len(classes))
    for k, (label, values, colour, alpha) in enumerate(series):
        v = [np.nan if values.get(c) is None else values[c] for c in classes]
        pos = x - 0.4 + (k + 0.5) * width
        if alpha is None:
            ax.bar(pos, v, width, label=label, fill=False, edgecolor=colour, hatch="//")
        else:
            ax.bar(pos, v, width, label=label, color=colour, alpha=alpha)
    ax.set_xticks(x, classes, rotation=30)
    ax.set_ylabel("F1")
    ax.set_ylim(0, 1.25)
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, ncol=3, loc="upper center")
    ax.set_title(f"Table I: per-class F1 ({doc['scale']} scale; paper hatched, real test frames)")
    fig.tight_layout()
    _save(fig, path, plt)


def _save(fig, path: Path, plt) -> None:
    """Atomic: render to bytes, then replace the file."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    with atomic_write(path) as f:
        f.write(buf.getvalue())


def _write_text(path: Path, text: str) -> None:
    with atomic_write(path) as f:
        f.write(text.encode())


def load(path: Path) -> dict:
    """A report JSON written by `write_all`, read back."""
    return json.loads(path.read_text())
