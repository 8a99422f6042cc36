"""Score a Segmenter on frames with ground truth: forest alone and forest + CRF.

The one scoring loop behind `topseg evaluate`, the experiments' points and training's
validation split. It takes any iterable of (depth, truth) pairs, so a caller may wrap it in
a progress bar or feed it a dataset (`dataset_frames`) or a recording's frames.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from topseg.core import crf
from topseg.core.metrics import ConfusionAccumulator
from topseg.core.segmenter import Segmenter


@dataclass
class Scores:
    """What `score` gathered: both confusions, summed stage times and the kept examples.

    forest    confusion of the forest's argmax
    crf       confusion of the Segmenter's labels (the same as `forest` when mode is none)
    examples  (depth, truth, forest labels, CRF labels) of the first frames, for pictures
    """

    crf_mode: str
    forest: ConfusionAccumulator = field(default_factory=ConfusionAccumulator)
    crf: ConfusionAccumulator = field(default_factory=ConfusionAccumulator)
    frames: int = 0
    forest_ms: float = 0.0
    crf_ms: float = 0.0
    examples: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=list
    )

    def ms_per_frame(self) -> dict[str, float]:
        """Mean milliseconds per frame of each stage: {"forest": ..., "crf": ...}."""
        n = max(self.frames, 1)
        return {"forest": self.forest_ms / n, "crf": self.crf_ms / n}


def score(
    segmenter: Segmenter,
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    *,
    examples: int = 0,
) -> Scores:
    """Label every (depth, truth) pair of `frames` and add it to both confusions; keep the
    first `examples` frames for pictures. A frame the Segmenter refuses raises its
    TopsegError (named `frame I`, I counting from 0)."""
    out = Scores(crf_mode=segmenter.crf_mode)
    for i, (depth, truth) in enumerate(frames):
        result = segmenter.label(depth, name=f"frame {i}")
        final = result.labels
        if segmenter.crf_mode == "none":
            pred = final
        else:
            pred = crf.segment_argmax(result.proba, np.asarray(depth) > 0)
        out.forest_ms += result.timings.forest_ms
        out.crf_ms += result.timings.crf_ms
        out.forest.add(truth, pred)
        out.crf.add(truth, final)
        out.frames += 1
        if len(out.examples) < examples:
            out.examples.append((depth, truth, pred, final))
    return out


def dataset_frames(ds, indices: Sequence[int] | range) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(depth, truth) arrays of the dataset frames at `indices`, read one at a time."""
    for i in indices:
        yield np.asarray(ds.depth[i]), np.asarray(ds.labels[i])
