"""Score a Segmenter on frames with ground truth: forest alone and forest + CRF.

The one scoring loop behind `topseg evaluate`, the experiments' points and training's
validation split. It takes any iterable of (depth, truth, mount) triples (each frame labelled
through its own mount; a (depth, truth) pair uses the Segmenter's), so a caller may wrap it
in a progress bar or feed it a dataset (`dataset_frames`) or a recording's frames.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from topseg.core.forest.inputs import dataset_mount
from topseg.core.metrics import ConfusionAccumulator, HeadDetections
from topseg.core.segmenter import Segmenter

if TYPE_CHECKING:
    from topseg.core.camera import TopViewMount


@dataclass
class Scores:
    """What `score` gathered: both confusions, summed stage times and the kept examples.

    forest       confusion of the forest's argmax
    crf          confusion of the Segmenter's labels (the same as `forest` when mode is none)
    heads        the Segmenter's labels' heads counted as blobs (`metrics.head_detections`)
    examples     (depth, truth, forest labels, CRF labels) of the first frames, for pictures
    floor_share  summed floor-gated shares (mean: `floor_share / frames`)
    frame_confusions  each frame's CRF confusion, in order, when `score` was asked to keep
                 them (bootstrap intervals: `metrics.avg_f1_draws`); else empty
    """

    crf_mode: str
    forest: ConfusionAccumulator = field(default_factory=ConfusionAccumulator)
    crf: ConfusionAccumulator = field(default_factory=ConfusionAccumulator)
    heads: HeadDetections = field(default_factory=HeadDetections)
    frames: int = 0
    forest_ms: float = 0.0
    crf_ms: float = 0.0
    floor_share: float = 0.0
    examples: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=list
    )
    frame_confusions: list[np.ndarray] = field(default_factory=list)

    def ms_per_frame(self) -> dict[str, float]:
        """Mean milliseconds per frame of each stage: {"forest": ..., "crf": ...}."""
        n = max(self.frames, 1)
        return {"forest": self.forest_ms / n, "crf": self.crf_ms / n}


def score(
    segmenter: Segmenter,
    frames: Iterable[tuple[np.ndarray, np.ndarray, TopViewMount | None]],
    *,
    examples: int = 0,
    keep_confusions: bool = False,
) -> Scores:
    """Label every (depth, truth, mount) triple of `frames` (a mount of None, or a (depth,
    truth) pair, takes the Segmenter's) and add it to both confusions; keep the first
    `examples` frames for pictures, and with `keep_confusions` each frame's CRF confusion.
    A frame the Segmenter refuses raises its TopsegError (named `frame I`, I counting
    from 0)."""
    out = Scores(crf_mode=segmenter.crf_mode)
    for i, item in enumerate(frames):
        depth, truth = item[0], item[1]
        mount = item[2] if len(item) > 2 else None
        result = segmenter.label(depth, name=f"frame {i}", mount=mount)
        final = result.labels
        pred = final if segmenter.crf_mode == "none" else result.forest_labels()
        out.forest_ms += result.timings.forest_ms
        out.crf_ms += result.timings.crf_ms
        out.floor_share += result.floor_share
        out.forest.add(truth, pred)
        frame = out.crf.add(truth, final)
        if keep_confusions:
            out.frame_confusions.append(frame)
        out.heads.add(truth, final)
        out.frames += 1
        if len(out.examples) < examples:
            out.examples.append((depth, truth, pred, final))
    return out


def dataset_frames(
    ds, indices: Sequence[int] | range
) -> Iterator[tuple[np.ndarray, np.ndarray, TopViewMount]]:
    """(depth, truth, mount) of the dataset frames at `indices`, read one at a time, each
    cropped to its mount's camera (a smaller sensor's frame is stored top-left)."""
    for i in indices:
        mount = dataset_mount(ds, i)
        h, w = mount.intrinsics.shape
        yield np.asarray(ds.depth[i])[:h, :w], np.asarray(ds.labels[i])[:h, :w], mount
