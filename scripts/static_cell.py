"""What the static cell's recorded background does on rendered cells (docs/performance.md).

For each of `--scenes` modeled scenes seen by a Kinect v1 at 3.5 m (640x480, its own noise)
it renders `--empty` frames of the scene without its person and fits their background
(`core.background.fit_background`), then labels `--frames` frames with the person through
the bundled model twice, without and with the background, and prints per scene and in all:
the pixels the forest may walk (with depth, not gated), the share of person pixels labelled
as a person, the pixels of furniture or floor labelled as a person, the worst share of the
background read farther than recorded (should stay far below the worker's 2 %), and the
median ms of the background stage, the forest, the CRF and the whole frame.

    python scripts/static_cell.py [--scenes 6] [--empty 40] [--frames 3] [--repeats 3]

Run it without `nice` on a machine not busy with other work: on two cores every parallel
kernel waits for both threads, and under load or a lower priority each such wait costs a
scheduler slice, which swamps the stages' own times.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from topseg.core import labels as L
from topseg.core.background import fit_background, save_background
from topseg.core.camera import PAPER_MOUNT
from topseg.core.segmenter import Segmenter
from topseg.core.segmenter_config import BackgroundConfig, SegmenterConfig
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer

MOUNT = replace(PAPER_MOUNT, sensor="kinect_v1")
STAGES = ("background", "forest", "crf")


def scene_frames(synth: Synthesizer, seed: int, empty: int, frames: int):
    """(frames of the scene without its person, frames with it) of scene `seed`."""
    scene = synth.density.sample(synth.rngs(seed)[0], MOUNT)
    person, scene.human = scene.human, None
    cell = [synth.render_scene(scene, np.random.default_rng(1000 + i)).depth for i in range(empty)]
    scene.human = person
    return cell, [synth.render_scene(scene, np.random.default_rng(5000 + i)) for i in range(frames)]


def walked(result) -> int:
    """Pixels of a labelled frame the forest could walk: with depth, not gated."""
    inp = result._frame.inp
    return int(np.count_nonzero((inp.values > 0) & ~inp.floor))


def measure(seg: Segmenter, frame, repeats: int) -> dict:
    """What one Segmenter does with one rendered frame (see the module)."""
    result = seg.label(frame.depth)
    person = np.isin(frame.labels, L.HUMAN_IDS)
    other = ~person & (frame.labels != L.NO_DEPTH)
    said_person = np.isin(result.labels, L.HUMAN_IDS)
    times = [seg.label(frame.depth).timings for _ in range(repeats)]
    return {
        "walked": walked(result),
        "person_px": int(person.sum()),
        "person_hit": int(said_person[person].sum()),
        "other_as_person": int(said_person[other].sum()),
        "missing_share": result.background_missing_share,
        **{name: [t.stages_ms[name] for t in times] for name in STAGES},
        "total": [t.total_ms for t in times],
    }


def summary(name: str, rows: list[dict]) -> str:
    """One line over `rows` of `measure`."""
    walk = [r["walked"] for r in rows]
    recall = sum(r["person_hit"] for r in rows) / max(1, sum(r["person_px"] for r in rows))
    ms = {k: float(np.median([x for r in rows for x in r[k]])) for k in (*STAGES, "total")}
    return (
        f"{name:>8}: forest may walk {min(walk)}-{max(walk)} px, person recall {recall:.3f}, "
        f"furniture or floor as person {sum(r['other_as_person'] for r in rows)} px, worst "
        f"missing share {max(r['missing_share'] for r in rows):.5f}; ms median "
        + ", ".join(f"{k} {v:.2f}" for k, v in ms.items())
    )


def main() -> None:
    """Render, fit, label, print (see the module)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--empty", type=int, default=40)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `topseg` runs kernels
    plain = Segmenter.from_file(None, SegmenterConfig(mount=MOUNT))
    rows: dict[str, list[dict]] = {"without": [], "with": []}
    config = SynthesisConfig(mode="modeled", seed=31, camera=MOUNT, noise="kinect")
    with tempfile.TemporaryDirectory() as tmp, Synthesizer(config) as synth:
        for seed in range(args.scenes):
            cell, frames = scene_frames(synth, seed, args.empty, args.frames)
            bg = fit_background(cell, MOUNT.intrinsics, "kinect_v1", MOUNT)
            path = Path(tmp) / f"scene{seed}.npz"
            save_background(path, bg)
            gated = Segmenter.from_file(
                None, SegmenterConfig(mount=MOUNT, background=BackgroundConfig(str(path)))
            )
            scene = {"without": [], "with": []}
            for frame in frames:
                for name, seg in (("without", plain), ("with", gated)):
                    seg.label(frame.depth)  # compiled and warm
                    scene[name].append(measure(seg, frame, args.repeats))
            print(
                f"scene {seed}: background {100 * bg.valid_share:.1f} %, unstable "
                f"{100 * bg.unstable_share:.2f} %, median sigma {bg.median_sigma_mm:.1f} mm"
            )
            for name, got in scene.items():
                print(summary(name, got))
                rows[name] += got
    print("all scenes:")
    for name, got in rows.items():
        print(summary(name, got))


if __name__ == "__main__":
    main()
