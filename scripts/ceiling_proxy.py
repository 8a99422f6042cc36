"""A stand-in for a real judging sequence, run the way it is run (docs/results.md).

Such frames (not in the repository) are a time-of-flight sequence from one ceiling, resampled to Kinect
v1 geometry (640x480, fx 570) and labelled by `topseg segment --out DIR FRAMES/` with no
mount given. This script renders a folder of such frames per ceiling height: one mount for
the folder (a little tilt), Kinect v1 intrinsics, time-of-flight noise, modeled scenes with
few pieces of furniture and people walking in and out of view (`--scene walker`: one person
walking or standing on an empty floor, the judging sequence's kind; `--native kinect_v2`:
rendered at that sensor's geometry and noise, then resampled to Kinect v1's, as the judging
frames were). It writes them as 16-bit PNGs
with their truth beside them, runs `topseg segment` on the folder as a user would (the
mount estimated from the frames), and scores what it wrote: person-pixel F1, furniture on a
person, head pixels, and heads as blobs (`metrics.head_detections`), also counted apart for
the heads that touch the image's border (`border_*`): on a person walking under the camera
they are a quarter to a half of the heads, and nearly every head missed is one of them.

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
from topseg.core.camera import Intrinsics, TopViewMount
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


def resample_coords(src: Intrinsics, dst: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) float64 in `src`'s image of each pixel of `dst`'s, for two cameras with
    the same centre and orientation: only the pixel grid changes, depth does not."""
    v, u = np.mgrid[0 : dst.height, 0 : dst.width].astype(np.float64)
    return src.cy + (v - dst.cy) * src.fy / dst.fy, src.cx + (u - dst.cx) * src.fx / dst.fx


def resample(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, linear: bool) -> np.ndarray:
    """`image` read at (rows, cols): nearest neighbour, or bilinear where all four
    neighbours have depth (nearest elsewhere, so that no-depth does not spread); 0 outside."""
    h, w = image.shape
    inside = (rows > -0.5) & (rows < h - 0.5) & (cols > -0.5) & (cols < w - 0.5)
    ri = np.clip(np.rint(rows), 0, h - 1).astype(np.intp)
    ci = np.clip(np.rint(cols), 0, w - 1).astype(np.intp)
    out = np.where(inside, image[ri, ci], 0).astype(image.dtype)
    if not linear:
        return out
    r0 = np.clip(np.floor(rows), 0, h - 2).astype(np.intp)
    c0 = np.clip(np.floor(cols), 0, w - 2).astype(np.intp)
    fr, fc = np.clip(rows - r0, 0, 1), np.clip(cols - c0, 0, 1)
    q = [image[r0 + dr, c0 + dc].astype(np.float64) for dr in (0, 1) for dc in (0, 1)]
    blend = (q[0] * (1 - fc) + q[1] * fc) * (1 - fr) + (q[2] * (1 - fc) + q[3] * fc) * fr
    whole = inside & (q[0] > 0) & (q[1] > 0) & (q[2] > 0) & (q[3] > 0)
    return np.where(whole, np.rint(blend), out).astype(image.dtype)


def render(
    folder: Path,
    height_m: float,
    frames: int,
    seed: int,
    noise: str,
    scene: str = "cell",
    native: str | None = None,
    linear: bool = False,
) -> None:
    """`frames` frames from one mount `height_m` up into folder/frames (PNG) and folder/truth
    at Kinect v1 geometry, of the `scene` kind (a key of SCENES). With `native` (a sensor
    name) they are rendered with that sensor's intrinsics and resampled to Kinect v1 geometry
    (nearest neighbour, or bilinear with `linear`), as the judging frames were."""
    depth_dir, truth_dir = folder / "frames", folder / "truth"
    if (truth_dir / f"{frames - 1:04d}.png").exists():
        return
    depth_dir.mkdir(parents=True, exist_ok=True)
    truth_dir.mkdir(parents=True, exist_ok=True)
    k = get_sensor("kinect_v1").intrinsics
    src = get_sensor(native).intrinsics if native else k
    mount = TopViewMount(src, 1000.0 * height_m, 1.0, -0.5, native or "kinect_v1")
    config = SynthesisConfig(
        mode="modeled", noise=noise, seed=seed, camera=mount, density=SCENES[scene]
    )
    synth = Synthesizer(config)
    rows, cols = resample_coords(src, k)
    for i in range(frames):
        frame = synth.render(frame_seed=i)
        depth = frame.depth[: src.height, : src.width].astype(np.uint16)
        truth = frame.labels[: src.height, : src.width].astype(np.uint8)
        if native:
            depth = resample(depth, rows, cols, linear)
            truth = np.where(depth > 0, resample(truth, rows, cols, False), L.NO_DEPTH)
        Image.fromarray(depth).save(depth_dir / f"{i:04d}.png")
        Image.fromarray(truth.astype(np.uint8)).save(truth_dir / f"{i:04d}.png")


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
        "border_head_blob_precision": heads.border_precision,
        "border_head_blob_recall": heads.border_recall,
        "border_true_heads": heads.border_true,
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
    parser.add_argument(
        "--native",
        default=None,
        help="render at this sensor's geometry, then resample to Kinect v1's (e.g. kinect_v2)",
    )
    parser.add_argument(
        "--linear", action="store_true", help="with --native: bilinear, not nearest neighbour"
    )
    args = parser.parse_args(ours)
    for i, height in enumerate(float(h) for h in args.heights.split(",")):
        folder = args.out / f"{height:.1f}m"
        render(
            folder, height, args.frames, args.seed + i, args.noise, args.scene, args.native,
            args.linear,
        )  # fmt: skip
        segment(folder, args.model, extra)
        result = {
            k: round(v, 3) if isinstance(v, float) else v for k, v in score_folder(folder).items()
        }
        line = {"height_m": height, "noise": args.noise, "scene": args.scene, **result}
        if args.native:
            line["native"] = args.native + (" bilinear" if args.linear else " nearest")
        print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
