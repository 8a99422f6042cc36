"""`topseg experiment mounts`: one model scored across camera mounts and sensors.

The camera is the user's, so a model must hold its accuracy on every ceiling: held-out
modeled scenes are rendered at five mounts (height / tilt: 2.5 m / 0, 3.0 m / 5, 3.5 m / 0,
4.0 m / 8, 4.5 m / 3 degrees) for each supported sensor, each with its own resolution,
intrinsics and noise family, and scored with the realtime CRF. Each cell is avg F1 over the
ten classes; the reference cell is Kinect v1 at 3.5 m straight down (the paper's setup),
and the table says how far every other cell is from it. `--baseline MODEL` scores a second
model on the same frames (a model whose header names no input reads raw depth and gets
no mount; it is run on every sensor's frames all the same, to show what it does there).

Frames are rendered in this process from seeds no training set uses (TEST_SEED), so every
model is scored on the very same frames. Each cell's gap to the reference comes with a 95 %
bootstrap interval over frames (`metrics.avg_f1_draws`, frame i of the cell resampled with
frame i of the reference): at 60 frames a cell the reference alone moved by 0.016 against
300, so a gap near MAX_GAP is read with its interval. Writes OUT/mounts.md, mounts.json and
mounts.png.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from topseg.core.atomic import atomic_write
from topseg.core.camera import TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.labels import PAPER_SCORED_IDS
from topseg.core.metrics import avg_f1_draws, person_scores
from topseg.core.scoring import score
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.core.segmenter_config import GridConfig
from topseg.core.sensors import get_sensor
from topseg.core.synth.synthesis import SENSOR_NOISE, SynthesisConfig, Synthesizer

#: (height m, tilt deg) of the five mounts the table scores; the tilt is split over pitch and
#: roll
MOUNTS: tuple[tuple[float, float], ...] = (
    (2.5, 0.0),
    (3.0, 5.0),
    (3.5, 0.0),
    (4.0, 8.0),
    (4.5, 3.0),
)
#: the cell every other is compared with: the paper's mount and sensor
REFERENCE = ("kinect_v1", 3.5, 0.0)
#: dataset seed of the held-out scenes (training sets use small seeds)
TEST_SEED = 424242
#: largest avg-F1 gap to the reference cell that counts as "the same" (the mounts table's
#: target, docs/results.md)
MAX_GAP = 0.03
#: the floor under which no cell may fall (the mounts table's target, docs/results.md)
MIN_F1 = 0.70
#: bootstrap resamples behind each gap's interval, and their seed
BOOTSTRAP_DRAWS = 2000
BOOTSTRAP_SEED = 0
#: the share of the bootstrap's gaps a cell's interval holds
INTERVAL = 0.95


@dataclass(frozen=True)
class Cell:
    """One sensor at one mount: its avg F1 (forest + CRF) and forest-alone avg F1, and the
    INTERVAL bootstrap interval of its avg F1 minus the reference's (NaN when the reference
    cell was not scored, and in reports that hold no intervals)."""

    sensor: str
    height_m: float
    tilt_deg: float
    avg_f1: float
    forest_f1: float
    floor_share: float
    frames: int
    person_f1: float = math.nan
    head_precision: float = math.nan
    head_recall: float = math.nan
    furniture_on_person: float = math.nan
    head_detection_precision: float = math.nan
    head_detection_recall: float = math.nan
    gap_low: float = math.nan
    gap_high: float = math.nan


def cell_mount(sensor_name: str, height_m: float, tilt_deg: float):
    """The mount of a cell: the sensor's intrinsics, the height, the tilt split 0.8 / 0.6
    over pitch and roll (so it is neither purely about one axis)."""
    sensor = get_sensor(sensor_name)
    pitch, roll = 0.8 * tilt_deg, 0.6 * tilt_deg
    return TopViewMount(sensor.intrinsics, 1000.0 * height_m, pitch, roll, sensor.name)


def render_cell(mount, frames: int, seed: int = TEST_SEED) -> list[tuple]:
    """(depth, truth, mount) of `frames` held-out modeled scenes seen from `mount`, with the
    mount's sensor noise."""
    config = SynthesisConfig(mode="modeled", noise=SENSOR_NOISE, seed=seed, camera=mount)
    synth = Synthesizer(config)
    try:
        out = []
        for i in range(frames):
            frame = synth.render(frame_seed=i)
            h, w = mount.intrinsics.shape
            out.append((frame.depth[:h, :w], frame.labels[:h, :w], frame.mount or mount))
        return out
    finally:
        close = getattr(synth, "close", None)
        if close is not None:
            close()


def score_cell(segmenter, frames: list[tuple], keep_confusions: bool = False) -> dict:
    """Scores of `segmenter` (its CRF) on `frames`: avg F1, forest-alone avg F1, mean floor
    share, and the person-level figures real frames are judged by (person-pixel F1, head
    precision and recall, furniture on a person, heads as blobs: `metrics.head_detections`);
    with `keep_confusions` also "frame_confusions", each frame's (N, C, C) CRF confusion."""
    result = score(segmenter, frames, keep_confusions=keep_confusions)
    crf = result.crf.scores()
    head = crf["per_class"]["head"]
    person = person_scores(result.crf.confusion)
    return {
        "avg_f1": float(crf["avg_f1_10"]),  # the paper's ten classes
        "forest_f1": float(result.forest.scores()["avg_f1_10"]),
        "floor_share": float(result.floor_share) / max(result.frames, 1),
        "person_f1": person["person_f1"],
        "head_precision": float(head["precision"]),
        "head_recall": float(head["recall"]),
        "furniture_on_person": person["furniture_on_person"],
        "head_detection_precision": result.heads.precision,
        "head_detection_recall": result.heads.recall,
    } | ({"frame_confusions": np.stack(result.frame_confusions)} if keep_confusions else {})


def run_mounts(
    model, baseline, sensors, frames: int, out: Path, progress=print, downsample=(None, None)
) -> dict:
    """Score `model` (and `baseline`, when given) on every cell; write and return the report.
    `downsample` is each one's `SegmenterConfig.downsample` (None: from each cell's mount)."""
    # no size check: a model that reads raw depth is run on every sensor's frames as they are
    configs = [
        SegmenterConfig(check_camera=False, grid=GridConfig(downsample=d)) for d in downsample
    ]
    models = {"model": Segmenter.from_file(model, configs[0], crf="realtime")}
    if baseline is not None:
        models["baseline"] = Segmenter.from_file(baseline, configs[1], crf="realtime")

    cells: dict[str, list[Cell]] = {name: [] for name in models}
    draws: dict[str, list] = {name: [] for name in models}  # each cell's bootstrap avg F1
    for sensor in sensors:
        for height, tilt in MOUNTS:
            mount = cell_mount(sensor, height, tilt)
            data = render_cell(mount, frames)
            for name, seg in models.items():
                got = score_cell(seg, data if seg.reads_height else _no_mount(data), True)
                frames_cm = got.pop("frame_confusions")
                draws[name].append(
                    avg_f1_draws(frames_cm, BOOTSTRAP_DRAWS, BOOTSTRAP_SEED, PAPER_SCORED_IDS)
                )
                cells[name].append(Cell(sensor, height, tilt, frames=len(data), **got))
                progress(
                    f"  {name:8s} {sensor:15s} {height:.1f} m {tilt:3.0f} deg: "
                    f"avg F1 {got['avg_f1']:.3f} (forest {got['forest_f1']:.3f}), person F1 "
                    f"{got['person_f1']:.3f}, head P/R {got['head_precision']:.2f}/"
                    f"{got['head_recall']:.2f} (blobs {got['head_detection_precision']:.2f}/"
                    f"{got['head_detection_recall']:.2f}), floor {got['floor_share']:.0%}"
                )
    cells = {name: with_gap_intervals(cs, draws[name]) for name, cs in cells.items()}
    report = {
        "mounts": [list(m) for m in MOUNTS],
        "sensors": list(sensors),
        "frames_per_cell": frames,
        "test_seed": TEST_SEED,
        "reference": list(REFERENCE),
        "models": {
            name: {
                "path": str(seg.path),
                "model_id": seg.model_id,
                "downsample": seg.config.grid.downsample or "auto",
            }
            for name, seg in models.items()
        },
        "cells": {name: [c.__dict__ for c in cs] for name, cs in cells.items()},
        "verdict": verdict(cells["model"]),
    }
    if "baseline" in models:
        report["comparison"] = mean_difference(
            cells["model"], draws["model"], cells["baseline"], draws["baseline"]
        )
    out.mkdir(parents=True, exist_ok=True)
    _write(out / "mounts.json", json.dumps(report, indent=1) + "\n")
    write_report(report, out)
    return report


def write_report(report: dict, out: Path) -> None:
    """Write OUT/mounts.md and mounts.png from a report (`run_mounts`'s mounts.json)."""
    _write(out / "mounts.md", markdown(report))
    figure(report, out / "mounts.png")


def read_report(out: Path) -> dict:
    """OUT/mounts.json as `run_mounts` wrote it, its verdict recomputed from its cells;
    TopsegError in one line when it is missing or unreadable."""
    path = out / "mounts.json"
    try:
        report = json.loads(path.read_text())
        report["verdict"] = verdict([Cell(**c) for c in report["cells"]["model"]])
    except FileNotFoundError:
        raise TopsegError(f"{path}: no such file; run the mounts experiment first") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TopsegError(f"{path}: not a mounts report ({exc})") from None
    return report


def _no_mount(data: list[tuple]) -> list[tuple]:
    """Frames for a model that reads raw depth: no mount goes with them."""
    return [(depth, truth) for depth, truth, _ in data]


def reference_f1(cells: list[Cell]) -> float:
    """avg F1 of the reference cell (Kinect v1, 3.5 m, straight down)."""
    for c in cells:
        if (c.sensor, c.height_m, c.tilt_deg) == REFERENCE:
            return c.avg_f1
    return math.nan


def _interval(differences) -> tuple[float, float]:
    """The central INTERVAL of bootstrap `differences` (NaN draws left out)."""
    tail = 100 * (1 - INTERVAL) / 2
    low, high = np.nanpercentile(differences, [tail, 100 - tail])
    return float(low), float(high)


def with_gap_intervals(cells: list[Cell], draws: list) -> list[Cell]:
    """`cells` with each one's INTERVAL bootstrap interval of its avg F1 minus the
    reference's, from every cell's bootstrap avg F1 (`metrics.avg_f1_draws` with
    BOOTSTRAP_DRAWS and BOOTSTRAP_SEED, in `cells`' order: a cell of as many frames as the
    reference is resampled in pairs with it); the cells as they are when the reference cell
    is not among them. A cell of another frame count gets no interval."""
    keys = [(c.sensor, c.height_m, c.tilt_deg) for c in cells]
    if REFERENCE not in keys:
        return list(cells)
    at = keys.index(REFERENCE)
    out = []
    for cell, d in zip(cells, draws, strict=True):
        if cell.frames != cells[at].frames:  # not the same frames: no paired interval
            out.append(cell)
            continue
        low, high = _interval(d - draws[at])
        out.append(replace(cell, gap_low=low, gap_high=high))
    return out


def mean_difference(
    model: list[Cell], model_draws: list, baseline: list[Cell], baseline_draws: list
) -> dict:
    """The model's mean avg F1 over its cells minus the baseline's, scored on the same frames,
    with its INTERVAL bootstrap interval: each cell's draws (as `with_gap_intervals` takes
    them) resample its frames by the same indices for both models, and each draw
    differences the two means."""
    m = float(np.mean([c.avg_f1 for c in model]))
    b = float(np.mean([c.avg_f1 for c in baseline]))
    low, high = _interval(np.mean(model_draws, 0) - np.mean(baseline_draws, 0))
    return {"mean_model": m, "mean_baseline": b, "difference": m - b, "low": low, "high": high}


def verdict(cells: list[Cell]) -> dict:
    """The table's two targets (docs/results.md): every cell within MAX_GAP of the reference, none below MIN_F1;
    how many cells pass each, and how many miss the first by more than sampling explains
    (the whole of their gap's interval beyond MAX_GAP)."""
    ref = reference_f1(cells)
    gaps = [abs(c.avg_f1 - ref) for c in cells]
    return {
        "reference_f1": ref,
        "largest_gap": max(gaps) if gaps else math.nan,
        "lowest_f1": min(c.avg_f1 for c in cells) if cells else math.nan,
        "all_within_gap": bool(gaps) and max(gaps) <= MAX_GAP,
        "none_below_floor": bool(cells) and min(c.avg_f1 for c in cells) >= MIN_F1,
        "cells": len(cells),
        "within_gap": sum(g <= MAX_GAP for g in gaps),
        "at_least_floor": sum(c.avg_f1 >= MIN_F1 for c in cells),
        "beyond_gap_surely": sum(c.gap_low > MAX_GAP or c.gap_high < -MAX_GAP for c in cells),
    }


def _table(report: dict, cells: list[dict], cell_text) -> list[str]:
    """Markdown lines of one table: a row per sensor, a column per mount, `cell_text(cell)`."""
    head = "| sensor | " + " | ".join(f"{h:.1f} m / {t:.0f} deg" for h, t in report["mounts"])
    lines = [head + " |", "|---" * (len(report["mounts"]) + 1) + "|"]
    for sensor in report["sensors"]:
        row = [c for c in cells if c["sensor"] == sensor]
        lines.append(f"| {sensor} | " + " | ".join(cell_text(c) for c in row) + " |")
    return [*lines, ""]


def markdown(report: dict) -> str:
    """The report as markdown tables: rows = sensors, columns = mounts, per model."""
    lines = [
        f"# Avg F1 (realtime CRF) across mounts and sensors, {report['frames_per_cell']} "
        f"held-out modeled frames per cell (seed {report['test_seed']})",
        "",
    ]
    for name, cells in report["cells"].items():
        model = report["models"][name]
        lines += [f"## {name}: {model['path']} (downsample {model.get('downsample', 1)})", ""]
        lines += _table(report, cells, lambda c: f"{c['avg_f1']:.3f}")
        lines += ["Person-pixel F1 / head precision / head recall / furniture on a person:", ""]
        lines += _table(
            report,
            cells,
            lambda c: (
                f"{c['person_f1']:.2f} / {c['head_precision']:.2f} / "
                f"{c['head_recall']:.2f} / {c['furniture_on_person']:.1%}"
            ),
        )
        lines += [
            f"Gap to the reference (cell minus reference) and its {INTERVAL:.0%} bootstrap "
            "interval over frames:",
            "",
        ]
        lines += _table(report, cells, _gap_text(cells))
        lines += ["Heads as blobs (`metrics.head_detections`): precision / recall:", ""]
        lines += _table(
            report,
            cells,
            lambda c: (
                f"{c.get('head_detection_precision', math.nan):.2f} / "
                f"{c.get('head_detection_recall', math.nan):.2f}"
            ),
        )
    v = report["verdict"]
    lines += [
        f"Model: reference cell (Kinect v1, 3.5 m, 0 deg) {v['reference_f1']:.3f}; largest gap "
        f"to it {v['largest_gap']:.3f} (target <= {MAX_GAP}); lowest cell {v['lowest_f1']:.3f} "
        f"(target >= {MIN_F1}). Cells within {MAX_GAP} of the reference: {v['within_gap']} of "
        f"{v['cells']} ({v['beyond_gap_surely']} beyond it by more than their interval); at "
        f"{MIN_F1:.2f} or more: {v['at_least_floor']} of {v['cells']}.",
        "",
    ]
    if "comparison" in report:
        d = report["comparison"]
        lines += [
            f"Mean avg F1 over the cells: model {d['mean_model']:.4f}, baseline "
            f"{d['mean_baseline']:.4f}; model minus baseline {d['difference']:+.4f} "
            f"({INTERVAL:.0%} bootstrap interval over frames, paired: "
            f"{d['low']:+.4f} to {d['high']:+.4f}).",
            "",
        ]
    return "\n".join(lines)


def _gap_text(cells: list[dict]):
    """The gap table's cell text: 'reference', or '-0.032 [-0.040, -0.024]' ('-' for an
    interval a report does not have)."""
    ref = reference_f1([Cell(**c) for c in cells])

    def text(c: dict) -> str:
        if (c["sensor"], c["height_m"], c["tilt_deg"]) == REFERENCE:
            return "reference"
        low, high = c.get("gap_low", math.nan), c.get("gap_high", math.nan)
        interval = "-" if math.isnan(low) else f"[{low:+.3f}, {high:+.3f}]"
        return f"{c['avg_f1'] - ref:+.3f} {interval}"

    return text


def figure(report: dict, path: Path) -> None:
    """Heat maps per model, sensors by mounts: each cell's avg F1 (and its gap to the model's
    reference cell) in numbers, coloured by that gap; a red frame round each cell that misses
    the table's targets (further than MAX_GAP from the reference, or below MIN_F1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    names = list(report["cells"])
    fig, axes = plt.subplots(1, len(names), figsize=(7.5 * len(names), 4.8), squeeze=False)
    fig.subplots_adjust(left=0.1, right=0.86, wspace=0.45, bottom=0.2)
    labels = [f"{h:.1f} m\n{t:.0f} deg" for h, t in report["mounts"]]
    span = 0.15
    for ax, name in zip(axes[0], names, strict=True):
        cells = [Cell(**c) for c in report["cells"][name]]
        ref = reference_f1(cells)
        rows = [[c for c in cells if c.sensor == s] for s in report["sensors"]]
        grid = np.array([[c.avg_f1 for c in row] for row in rows])
        im = ax.imshow(grid - ref, vmin=-span, vmax=span, cmap="RdBu")
        for (i, j), v in np.ndenumerate(grid):
            c = rows[i][j]
            is_ref = (c.sensor, c.height_m, c.tilt_deg) == REFERENCE
            text = f"{v:.3f}\nreference" if is_ref else f"{v:.3f}\n{v - ref:+.3f}"
            colour = "white" if abs(v - ref) > 0.6 * span else "black"
            ax.text(j, i - 0.08, text, ha="center", va="center", fontsize=8,
                    fontweight="bold" if is_ref else "normal", color=colour)  # fmt: skip
            if not is_ref and not math.isnan(c.gap_low):
                ax.text(j, i + 0.3, f"{c.gap_low:+.3f}..{c.gap_high:+.3f}", ha="center",
                        va="center", fontsize=6, color=colour)  # fmt: skip
            if abs(v - ref) > MAX_GAP or v < MIN_F1:
                ax.add_patch(Rectangle((j - 0.46, i - 0.46), 0.92, 0.92, fill=False,
                                       edgecolor="red", linewidth=2))  # fmt: skip
        ax.set_xticks(range(len(labels)), labels, fontsize=8)
        ax.set_yticks(range(len(report["sensors"])), report["sensors"], fontsize=8)
        model = report["models"][name]
        title = model.get("label") or f"{model['path']} (downsample {model.get('downsample', 1)})"
        ax.set_title(f"{name}: {title}", fontsize=9)
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="avg F1 minus the reference cell")
    fig.text(0.1, 0.02, f"realtime CRF, {report['frames_per_cell']} frames a cell; under each gap "
             f"its {INTERVAL:.0%} bootstrap interval over frames;\nred frame: more than "
             f"{MAX_GAP} from the reference cell or below {MIN_F1:.2f}", fontsize=8)  # fmt: skip
    with _atomic(path) as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)


def _write(path: Path, text: str) -> None:
    with _atomic(path) as f:
        f.write(text.encode())


def _atomic(path: Path):
    return atomic_write(path)
