"""A stand-in for the real frames that judge issue 14, run the way they are run.

Those frames (not shared) are a time-of-flight sequence from one ceiling, resampled to Kinect
v1 geometry (640x480, fx 570) and labelled by `topseg segment --out DIR FRAMES/` with no
mount given. This script renders a folder of such frames per ceiling height: one mount for
the folder (a little tilt), Kinect v1 intrinsics, time-of-flight noise, modeled scenes with
few pieces of furniture and people walking in and out of view. It writes them as 16-bit PNGs
with their truth beside them, runs `topseg segment` on the folder as a user would (the
mount estimated from the frames), and scores what it wrote: person-pixel F1, furniture on a
person, head pixels, and heads as blobs (`metrics.head_detections`).

    python scripts/ceiling_proxy.py --out /tmp/proxy [--heights 2.7,3.3,3.9] [--frames 300]

300 frames a ceiling hold 80-130 true heads; at 80 frames (20-25 heads) one head moves a
head-blob figure by ~0.04, and the figures moved by 0.05 between seeds.

Extra `topseg segment` options go after `--`, e.g. `-- --min-head-cm2 0`. Frames already
rendered in OUT are reused. Prints one JSON line per height.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from topseg.core import labels as L
from topseg.core.camera import TopViewMount
from topseg.core.metrics import HeadDetections, confusion_matrix, person_scores, scores
from topseg.core.sensors import get_sensor
from topseg.core.synth.density import DensityConfig
from topseg.core.synth.synthesis import SynthesisConfig, Synthesizer


#: the scenes each stand-in renders: "cell" (a robot cell: 0-2 pieces of furniture, a person in
#: any of the density function's poses, sitting on a chair included) or "walker" (the judging
#: sequence's kind: one person walking or standing on an empty floor)
SCENES = {
    "cell": DensityConfig(n_objects=(0, 2), human_edge_share=0.3),
    "walker": DensityConfig(
        n_objects=(0, 0),
        human_edge_share=0.3,
        pose_weights={"walking": 3.0, "standing": 1.0},
        ho_relation_weights={"free": 1.0},
    ),
}


def render(
    folder: Path, height_m: float, frames: int, seed: int, noise: str, scene: str = "cell"
) -> None:
    """`frames` frames from one mount `height_m` up into folder/frames (PNG) and folder/truth,
    of the `scene` kind (a key of SCENES)."""
    depth_dir, truth_dir = folder / "frames", folder / "truth"
    if (truth_dir / f"{frames - 1:04d}.png").exists():
        return
    depth_dir.mkdir(parents=True, exist_ok=True)
    truth_dir.mkdir(parents=True, exist_ok=True)
    k = get_sensor("kinect_v1").intrinsics
    mount = TopViewMount(k, 1000.0 * height_m, 1.0, -0.5, "kinect_v1")
    config = SynthesisConfig(
        mode="modeled", noise=noise, seed=seed, camera=mount, density=SCENES[scene]
    )
    synth = Synthesizer(config)
    for i in range(frames):
        frame = synth.render(frame_seed=i)
        Image.fromarray(frame.depth[: k.height, : k.width].astype(np.uint16)).save(
            depth_dir / f"{i:04d}.png"
        )
        Image.fromarray(frame.labels[: k.height, : k.width].astype(np.uint8)).save(
            truth_dir / f"{i:04d}.png"
        )


def segment(folder: Path, model: str | None, extra: list[str]) -> None:
    """`topseg segment` on folder/frames into folder/pred, with no mount, as a user runs it."""
    cli = Path(sys.executable).parent / "topseg"
    cmd = [str(cli), "segment", "--out", str(folder / "pred"), str(folder / "frames"), *extra]
    if model:
        cmd += ["--model", model]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def score_folder(folder: Path) -> dict:
    """Person-level and head scores of folder/pred against folder/truth."""
    confusion = np.zeros((L.NUM_CLASSES, L.NUM_CLASSES), np.int64)
    heads = HeadDetections()
    for truth_png in sorted((folder / "truth").glob("*.png")):
        truth = np.asarray(Image.open(truth_png))
        pred = np.asarray(Image.open(folder / "pred" / f"{truth_png.stem}_labels.png"))
        confusion += confusion_matrix(truth, pred)
        heads.add(truth, pred)
    person, s = person_scores(confusion), scores(confusion)
    head = s["per_class"]["head"]
    return {
        "person_f1": person["person_f1"],
        "furniture_on_person": person["furniture_on_person"],
        "head_pixel_precision": head["precision"],
        "head_pixel_recall": head["recall"],
        "head_blob_precision": heads.precision,
        "head_blob_recall": heads.recall,
        "true_heads": heads.true,
        "predicted_heads": heads.predicted,
        "avg_f1": s["avg_f1"],
    }


def main(argv: list[str] | None = None) -> int:
    """Render, segment and score every height; one JSON line each."""
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    ours = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--heights", default="2.7,3.3,3.9", help="ceiling heights (m)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--noise", default="tof")
    parser.add_argument("--seed", type=int, default=501, help="first height's seed; +1 a height")
    parser.add_argument("--model", default=None, help="default: the bundled model")
    parser.add_argument("--scene", choices=sorted(SCENES), default="cell", help="what is in view")
    args = parser.parse_args(ours)
    for i, height in enumerate(float(h) for h in args.heights.split(",")):
        folder = args.out / f"{height:.1f}m"
        render(folder, height, args.frames, args.seed + i, args.noise, args.scene)
        segment(folder, args.model, extra)
        result = {
            k: round(v, 3) if isinstance(v, float) else v for k, v in score_folder(folder).items()
        }
        line = {"height_m": height, "noise": args.noise, "scene": args.scene, **result}
        print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
