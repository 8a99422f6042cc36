"""Score a model on a dataset: the paper's per-class table, JSON, and pictures.

The forest runs on every complete frame of the dataset; the CRF mode (`none`, `exact`,
`realtime`) smooths its posteriors. Prints the per-class precision / recall / F1 table
(Table I's layout) with mAP, mAR and avg F1 over ids 1..10, and with `--plots DIR` draws the
confusion matrix and a few frames (depth, truth, forest, CRF) side by side.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model file from `topseg train`")
    parser.add_argument("--data", required=True, type=Path, help="dataset from `topseg datagen`")
    parser.add_argument("--crf", choices=("none", "exact", "realtime"), default="realtime")
    parser.add_argument("--frames", type=int, default=None, help="score only the first N frames")
    parser.add_argument("--json", type=Path, dest="json_out", help="write the scores as JSON here")
    parser.add_argument("--plots", type=Path, help="write confusion.png and frames.png here")
    parser.add_argument("--examples", type=int, default=4, help="frames drawn in frames.png")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from topseg.core import crf, forest, metrics
    from topseg.core.formats.dataset import open_dataset

    model, _ = forest.load_model(args.model)
    ds = open_dataset(args.data)
    n = len(ds) if args.frames is None else min(args.frames, len(ds))
    config = crf.CRFConfig(mode=args.crf)
    raw, smooth = metrics.ConfusionAccumulator(), metrics.ConfusionAccumulator()
    examples = []
    seconds = {"forest": 0.0, "crf": 0.0}
    for i in tqdm(range(n), desc="evaluate", unit="frame", disable=None):
        depth, truth = np.asarray(ds.depth[i]), np.asarray(ds.labels[i])
        t0 = time.perf_counter()
        proba = forest.predict_proba(model, depth)
        t1 = time.perf_counter()
        pred = forest.labels_from_proba(proba, depth)
        final = pred if args.crf == "none" else crf.segment_crf(proba, depth, config)
        t2 = time.perf_counter()
        seconds["forest"] += t1 - t0
        seconds["crf"] += t2 - t1
        raw.add(truth, pred)
        smooth.add(truth, final)
        if len(examples) < args.examples:
            examples.append((depth, truth, pred, final))

    forest_scores, final_scores = raw.scores(), smooth.scores()
    print(metrics.format_table(forest_scores, title=f"forest alone, {n} frames of {args.data}"))
    if args.crf != "none":
        print()
        print(metrics.format_table(final_scores, title=f"forest + CRF ({args.crf})"))
    timing = {k: 1000 * v / max(n, 1) for k, v in seconds.items()}
    print(f"\nms per frame: forest {timing['forest']:.1f}, crf {timing['crf']:.1f}")

    if args.json_out:
        doc = json.loads(metrics.to_json(final_scores))
        doc.update(
            crf=args.crf,
            model=str(args.model),
            data=str(args.data),
            forest_only=json.loads(metrics.to_json(forest_scores)),
            ms_per_frame=timing,
            confusion=smooth.confusion.tolist(),
        )
        _write_text(args.json_out, json.dumps(doc, indent=2))
    if args.plots:
        from topseg.services.plots import confusion_figure, frames_figure

        args.plots.mkdir(parents=True, exist_ok=True)
        confusion_figure(smooth.confusion, args.plots / "confusion.png", title=f"CRF: {args.crf}")
        frames_figure(examples, args.plots / "frames.png", crf_name=args.crf)
        print(f"wrote {args.plots / 'confusion.png'} and {args.plots / 'frames.png'}")
    return 0


def _write_text(path: Path, text: str) -> None:
    """Atomic: a reader sees the old file or the whole new one."""
    from topseg.core.atomic import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        f.write((text + "\n").encode())
