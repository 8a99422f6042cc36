"""`topseg experiment open-world`: does a model call a robot, a box or a cabinet a person?

Held-out robot cells (`--mode cell` scenes from seeds no training set uses, none of them the
paper's office scenes) are rendered at the mounts table's five mounts for each sensor, with
the sensor's noise, and labelled with the realtime CRF. Every (sensor, mount) pair draws its
own cells (`cells_seed`), so 20 pairs of 30 cells are 600 different scenes. The report holds, over all cells:

| figure | what it counts | target |
|---|---|---|
| robot -> human | share of robot pixels labelled as a body part | <= 2 % |
| robot -> robot | share of robot pixels labelled robot | >= 90 % |
| object -> human | share of object pixels labelled as a body part | <= 2 % |
| phantom frames | frames with no person pixel whose labels hold a body-part blob of 150 cm2 or more on the floor | <= 2 % |
| person F1 | person pixels (any body part) against the rest | >= 0.95 |
| pose found | share of visible people of a pose with half their pixels or more labelled as body parts | >= 95 % each |

A person is visible with at least `MIN_VISIBLE_CM2` of their body in view; with two people
in a frame, each body-part pixel of the truth goes to the person whose projected trunk is
nearest its connected blob. `--background` also scores each frame with the scene's static
cell recorded as a background (its empty scene rendered `BACKGROUND_FRAMES` times with
noise), to show what the gate adds; the targets are the model's alone.
`--cells generated` scores cells of shapes drawn from generators rather than the density
function's own mix of catalogues and generators: every robot a random arm (`random_arms`), every item that can be one a mesh object (`mesh_objects`),
from their own seeds (`GENERATED_SEED`): the nearest rendered stand-in for a cell with robots
and objects nobody modelled.
Writes OUT/open-world.md and open-world.json.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from topseg.core import labels as L
from topseg.core.atomic import atomic_write
from topseg.core.camera import project
from topseg.core.metrics import ConfusionAccumulator, person_scores
from topseg.core.segmenter import Segmenter, SegmenterConfig
from topseg.core.synth.cell_scenes import CellConfig
from topseg.core.synth.density import DensityConfig
from topseg.core.synth.static_cell import BACKGROUND_FRAMES, static_background
from topseg.core.synth.synthesis import SENSOR_NOISE, SynthesisConfig, Synthesizer
from topseg.services.batch.experiment.mounts import MOUNTS, cell_mount

#: dataset seed of the held-out cells (training sets use small seeds; the mounts table 424242);
#: the (sensor, mount) pair of index k draws its cells from TEST_SEED + k
TEST_SEED = 515151
#: a predicted body-part blob this large (cm2 on the floor) in a frame without a person is a
#: phantom person
PHANTOM_CM2 = 150.0
#: a person with less of their body in view than this (cm2) is not counted for pose recall
MIN_VISIBLE_CM2 = 150.0
#: share of a person's pixels that must be labelled as body parts for them to be found
FOUND_SHARE = 0.5
#: dataset seed of the `generated` cells (the pair of index k: GENERATED_SEED + k)
GENERATED_SEED = 535353
#: what each kind of held-out cell changes in the density function's cells
CELLS = {
    "default": {},
    "generated": {"robot_names": ("random",), "mesh_share": 1.0},
}
#: the poses the report names (every other pose is counted under its own name too)
SCORED_POSES = ("standing", "reaching", "kneeling", "crouching", "lying")
TARGETS = {
    "robot_as_human": ("<=", 0.02),
    "robot_as_robot": (">=", 0.90),
    "object_as_human": ("<=", 0.02),
    "phantom_frames": ("<=", 0.02),
    "person_f1": (">=", 0.95),
    "pose_found": (">=", 0.95),
}


def pixel_area_cm2(depth_mm: np.ndarray, mount) -> np.ndarray:
    """Each pixel's footprint (cm2) on a surface facing the camera at its depth."""
    k = mount.intrinsics
    z_cm = depth_mm.astype(np.float64) / 10.0
    return z_cm * z_cm / (k.fx * k.fy)


def blob_areas_cm2(mask: np.ndarray, area: np.ndarray) -> np.ndarray:
    """The area (cm2) of each 8-connected blob of `mask`."""
    lab, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros(0)
    return np.bincount(lab.ravel(), weights=area.ravel(), minlength=n + 1)[1:]


def person_masks(truth: np.ndarray, scene: dict, mount) -> list[np.ndarray]:
    """One truth mask per person of `scene` (its body-part pixels), in `Scene.humans` order."""
    people = ([scene["human"]] if scene.get("human") else []) + scene.get("extra_humans", [])
    human = np.isin(truth, L.HUMAN_IDS)
    if len(people) <= 1:
        return [human] if people else []
    trunks = np.array([[p["x"], p["y"], p["z"]] for p in people], np.float64)
    uv = project(mount.world_to_camera(trunks), mount.intrinsics)
    lab, n = ndimage.label(human, structure=np.ones((3, 3), bool))
    masks = [np.zeros_like(human) for _ in people]
    if n == 0:
        return masks
    centres = np.array(ndimage.center_of_mass(human, lab, range(1, n + 1)))  # (row, col)
    for blob, (r, c) in enumerate(centres, start=1):
        nearest = int(np.argmin(np.hypot(uv[:, 0] - c, uv[:, 1] - r)))
        masks[nearest] |= lab == blob
    return masks


@dataclass
class OpenWorldTally:
    """Running counts of the report's figures over frames."""

    confusion: ConfusionAccumulator = field(default_factory=ConfusionAccumulator)
    frames: int = 0
    empty_frames: int = 0
    phantom_frames: int = 0
    poses: dict = field(default_factory=dict)  # pose -> [found, visible]

    def add(self, truth, pred, depth, mount, scene: dict) -> None:
        """Count one labelled frame."""
        self.confusion.add(truth, pred)
        self.frames += 1
        area = pixel_area_cm2(depth, mount)
        person_pred = np.isin(pred, L.HUMAN_IDS)
        if not np.isin(truth, L.HUMAN_IDS).any():
            self.empty_frames += 1
            if (blob_areas_cm2(person_pred, area) >= PHANTOM_CM2).any():
                self.phantom_frames += 1
        people = ([scene["human"]] if scene.get("human") else []) + scene.get("extra_humans", [])
        for person, mask in zip(people, person_masks(truth, scene, mount), strict=True):
            if area[mask].sum() < MIN_VISIBLE_CM2:
                continue
            found = person_pred[mask].mean() >= FOUND_SHARE
            tally = self.poses.setdefault(person["pose"], [0, 0])
            tally[0] += int(found)
            tally[1] += 1

    def figures(self) -> dict:
        """The report's figures (NaN where nothing was there to count)."""
        cm = self.confusion.confusion.astype(np.float64)
        human = list(L.HUMAN_IDS)

        def share(truth_id, pred_ids) -> float:
            row = cm[truth_id]
            return float(row[pred_ids].sum() / row.sum()) if row.sum() else math.nan

        scores = self.confusion.scores()
        return {
            "frames": self.frames,
            "robot_pixels": int(cm[L.ROBOT].sum()),
            "object_pixels": int(cm[L.OBJECT].sum()),
            "robot_as_human": share(L.ROBOT, human),
            "robot_as_robot": share(L.ROBOT, [L.ROBOT]),
            "object_as_human": share(L.OBJECT, human),
            "object_as_object": share(L.OBJECT, [L.OBJECT]),
            "furniture_as_human": float(
                cm[np.ix_(list(L.FURNITURE_IDS), human)].sum()
                / max(cm[list(L.FURNITURE_IDS)].sum(), 1)
            ),
            "empty_frames": self.empty_frames,
            "phantom_frames": self.phantom_frames / self.empty_frames
            if self.empty_frames
            else math.nan,
            **person_scores(self.confusion.confusion),
            "avg_f1": scores["avg_f1"],
            "avg_f1_10": scores.get("avg_f1_10", math.nan),
            "poses": {
                p: {"found": f, "visible": n, "share": f / n if n else math.nan}
                for p, (f, n) in sorted(self.poses.items())
            },
        }


def cells_seed(sensor_index: int, mount_index: int, base: int = TEST_SEED) -> int:
    """The dataset seed of the cells the `sensor_index`-th sensor sees from the
    `mount_index`-th mount: each pair its own scenes."""
    return base + sensor_index * len(MOUNTS) + mount_index


def cell_config(mount, seed: int = TEST_SEED, cells: str = "default") -> SynthesisConfig:
    """The held-out cells seen from `mount`: robot cells only (no paper scenes), each sensor's
    own noise; `cells` one of CELLS."""
    density = DensityConfig(cell=CellConfig(paper_share=0.0, **CELLS[cells]))
    return SynthesisConfig(mode="cell", noise=SENSOR_NOISE, seed=seed, camera=mount,
                           density=density)  # fmt: skip


def render_cells(
    mount, frames: int, seed: int = TEST_SEED, background: bool = False, cells: str = "default"
) -> list[tuple]:
    """(depth, truth, mount, scene dict, background) of `frames` held-out cells (`cells`, one
    of CELLS) seen from `mount`; with `background`, each cell's static background (else
    None)."""
    with Synthesizer(cell_config(mount, seed, cells)) as synth:
        out = []
        for i in range(frames):
            f = synth.render(frame_seed=i)
            m = f.mount or mount
            bg = static_background(synth, f.scene, m, seed=i) if background else None
            out.append((f.depth, f.labels, m, f.scene, bg))
        return out


def verdict(figures: dict) -> dict:
    """Each target met (True/False; None where nothing was counted)."""
    out = {}
    for key, (op, bound) in TARGETS.items():
        if key == "pose_found":
            shares = [figures["poses"].get(p, {}).get("share", math.nan) for p in SCORED_POSES]
            value = min((s for s in shares if not math.isnan(s)), default=math.nan)
        else:
            value = figures[key]
        out[key] = None if math.isnan(value) else (value <= bound if op == "<=" else value >= bound)
    return out


def run_open_world(
    model,
    sensors,
    frames: int,
    out: Path,
    progress=print,
    background: bool = False,
    cells: str = "default",
) -> dict:
    """Score `model` on held-out cells (`cells`, one of CELLS) at every mount and sensor
    (and, with `background`, again with each cell's static background gating it); write and
    return the report."""
    if cells not in CELLS:
        raise ValueError(f"cells must be one of {', '.join(CELLS)}, got {cells!r}")
    base = TEST_SEED if cells == "default" else GENERATED_SEED
    seg = Segmenter.from_file(model, SegmenterConfig(check_camera=False), crf="realtime")
    total, total_bg = OpenWorldTally(), OpenWorldTally()
    per_sensor: dict[str, dict] = {}
    for si, sensor in enumerate(sensors):
        tally = OpenWorldTally()
        for mi, (height, tilt) in enumerate(MOUNTS):
            mount = cell_mount(sensor, height, tilt)
            seed = cells_seed(si, mi, base)
            for depth, truth, m, scene, bg in render_cells(mount, frames, seed, background, cells):
                pred = seg.label(depth, mount=m).labels
                tally.add(truth, pred, depth, m, scene)
                total.add(truth, pred, depth, m, scene)
                if bg is not None:
                    gated = seg.with_background(bg)
                    total_bg.add(truth, gated.label(depth, mount=m).labels, depth, m, scene)
        per_sensor[sensor] = tally.figures()
        f = per_sensor[sensor]
        progress(
            f"  {sensor:15s} robot->human {f['robot_as_human']:.1%} robot->robot "
            f"{f['robot_as_robot']:.1%} object->human {f['object_as_human']:.1%} phantom frames "
            f"{f['phantom_frames']:.1%} person F1 {f['person_f1']:.3f}"
        )
    figures = total.figures()
    report = {
        "model": {"path": str(seg.path), "model_id": seg.model_id},
        "mounts": [list(m) for m in MOUNTS],
        "sensors": list(sensors),
        "frames_per_mount": frames,
        "test_seed": base,
        "cells": cells,
        "targets": {k: list(v) for k, v in TARGETS.items()},
        "all": figures,
        "per_sensor": per_sensor,
        "verdict": verdict(figures),
    }
    if background:
        report["with_background"] = total_bg.figures()
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "open-world.json") as fh:
        fh.write((json.dumps(_nan_none(report), indent=1) + "\n").encode())
    with atomic_write(out / "open-world.md") as fh:
        fh.write(markdown(report).encode())
    return report


def _nan_none(x):
    """`x` with every NaN float replaced by None (JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: _nan_none(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_nan_none(v) for v in x]
    return None if isinstance(x, float) and math.isnan(x) else x


def _pct(x) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.1%}"


def markdown(report: dict) -> str:
    """The report as a Markdown page: the targets, then per sensor, then per pose."""
    a, v = report["all"], report["verdict"]
    ok = {True: "met", False: "**missed**", None: "n/a"}
    lines = [
        "# Open world: robots, objects and people in held-out cells",
        "",
        f"Model `{report['model']['path']}` ({report['model']['model_id']}); "
        f"{report['frames_per_mount']} cells per mount x {len(report['mounts'])} mounts x "
        f"{len(report['sensors'])} sensors = {a['frames']} frames of {report['cells']} cells, "
        f"test seed {report['test_seed']}; realtime CRF.",
        "",
        "| figure | value | target | |",
        "|---|---|---|---|",
    ]
    for key, (op, bound) in report["targets"].items():
        if key == "pose_found":
            val = min(
                (a["poses"][p]["share"] for p in SCORED_POSES
                 if p in a["poses"] and not math.isnan(a["poses"][p]["share"])),
                default=math.nan,
            )  # fmt: skip
            shown = _pct(val) + " (lowest pose)"
        elif key == "person_f1":
            shown = f"{a[key]:.3f}"
        else:
            shown = _pct(a[key])
        target = f"{op} {bound:.0%}" if bound < 0.5 or key != "person_f1" else f"{op} {bound}"
        lines.append(f"| {key.replace('_', ' ')} | {shown} | {target} | {ok[v[key]]} |")
    lines += [
        "",
        f"Robot pixels {a['robot_pixels']}, object pixels {a['object_pixels']}, frames without "
        f"a person {a['empty_frames']}; object -> object {_pct(a['object_as_object'])}, "
        f"furniture -> human {_pct(a['furniture_as_human'])}; avg F1 over twelve classes "
        f"{a['avg_f1']:.3f}, over the paper's ten {a['avg_f1_10']:.3f}.",
        "",
        "| sensor | robot -> human | robot -> robot | object -> human | phantom frames | person F1 |",
        "|---|---|---|---|---|---|",
    ]
    for sensor, f in report["per_sensor"].items():
        lines.append(
            f"| {sensor} | {_pct(f['robot_as_human'])} | {_pct(f['robot_as_robot'])} | "
            f"{_pct(f['object_as_human'])} | {_pct(f['phantom_frames'])} | {f['person_f1']:.3f} |"
        )
    lines += ["", "| pose | found | visible | share |", "|---|---|---|---|"]
    for pose, p in a["poses"].items():
        lines.append(f"| {pose} | {p['found']} | {p['visible']} | {_pct(p['share'])} |")
    b = report.get("with_background")
    if b:
        lines += [
            "",
            "With each cell's static background recorded (its empty scene, "
            f"{BACKGROUND_FRAMES} frames) and gating the frames:",
            "",
            "| | robot -> human | robot -> robot | object -> human | phantom frames | person F1 |"
            " lowest pose found |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, f in (("model alone", a), ("with background", b)):
            low = min((p["share"] for k, p in f["poses"].items() if k in SCORED_POSES
                       and not math.isnan(p["share"])), default=math.nan)  # fmt: skip
            lines.append(
                f"| {name} | {_pct(f['robot_as_human'])} | {_pct(f['robot_as_robot'])} | "
                f"{_pct(f['object_as_human'])} | {_pct(f['phantom_frames'])} | "
                f"{f['person_f1']:.3f} | {_pct(low)} |"
            )
    return "\n".join(lines) + "\n"


__all__ = ["OpenWorldTally", "cells_seed", "render_cells", "run_open_world"]
