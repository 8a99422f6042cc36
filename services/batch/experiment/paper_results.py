"""The paper's published numbers (Sharma et al. 2016), as data to draw and tabulate beside ours.

Copied from `../shared/paper/sharma2016.tex`: the pgfplots coordinates of Fig. 4 and
Table I (tests/test_experiment.py parses the .tex and checks every number here). The paper
scored all of them on 65 real Kinect frames; topseg scores on a held-out synthetic set with
the Kinect noise model, so the comparison is of trends, not of exact values.

The paper gives no numbers for the theta' (overlap) sweep, only that performance rises up to
theta' = 30 % and falls sharply after it (section "Comparison of Models").
"""

from __future__ import annotations

from topseg.core import labels

# Fig. 4: metric -> curve name -> [(x, value), ...]
NOISE: dict[str, dict[str, list[tuple[float, float]]]] = {
    "mAR": {
        "gaussian": [
            (0, 0.776),
            (5, 0.834),
            (10, 0.855),
            (15, 0.856),
            (30, 0.835),
            (50, 0.731),
            (100, 0.273),
        ]
    },
    "mAP": {
        "gaussian": [
            (0, 0.589),
            (5, 0.644),
            (10, 0.664),
            (15, 0.667),
            (30, 0.651),
            (50, 0.572),
            (100, 0.287),
        ]
    },
}

FEATURES: dict[str, dict[str, list[tuple[float, float]]]] = {
    "mAR": {
        "linear": [(75, 0.794), (150, 0.81), (300, 0.828), (400, 0.83), (500, 0.836), (600, 0.835)],
        "axis": [(75, 0.685), (150, 0.702), (300, 0.715), (400, 0.720), (500, 0.723), (600, 0.725)],
    },
    "mAP": {
        "linear": [
            (75, 0.613),
            (150, 0.630),
            (300, 0.645),
            (400, 0.646),
            (500, 0.652),
            (600, 0.654),
        ],
        "axis": [(75, 0.564), (150, 0.578), (300, 0.592), (400, 0.597), (500, 0.602), (600, 0.605)],
    },
}

FRAMES: dict[str, dict[str, list[tuple[float, float]]]] = {
    "mAR": {
        "modeled": [
            (40, 0.6436),
            (200, 0.7341),
            (400, 0.7613),
            (1200, 0.8003),
            (1600, 0.8066),
            (2400, 0.8160),
            (4800, 0.8289),
        ],
        "non-modeled": [
            (40, 0.6357),
            (200, 0.7131),
            (400, 0.7264),
            (1200, 0.7489),
            (1600, 0.7611),
            (2400, 0.7641),
            (4800, 0.7676),
        ],
    },
    "mAP": {
        "modeled": [
            (40, 0.5443),
            (200, 0.6177),
            (400, 0.6459),
            (1200, 0.6836),
            (1600, 0.6904),
            (2400, 0.6939),
            (4800, 0.7117),
        ],
        "non-modeled": [
            (40, 0.4603),
            (200, 0.5623),
            (400, 0.5770),
            (1200, 0.6023),
            (1600, 0.6117),
            (2400, 0.6236),
            (4800, 0.6289),
        ],
    },
}

OVERLAP: dict[str, dict[str, list[tuple[float, float]]]] = {"mAR": {}, "mAP": {}}

#: Fig. 4 by experiment name
CURVES = {"noise": NOISE, "features": FEATURES, "frames": FRAMES, "overlap": OVERLAP}

# Table I: F1 with the CRF, per class in topseg's label names, and the average. The paper's
# columns are the scored classes in the label table's order (tests/test_experiment.py checks
# them against the .tex by name).
TABLE_CLASSES: tuple[str, ...] = tuple(labels.name_of(i) for i in labels.PAPER_SCORED_IDS)
TABLE_I: dict[str, dict[str, float]] = {
    "non-modeled": dict(
        zip(
            ("avg", *TABLE_CLASSES),
            (0.76, 0.90, 0.71, 0.73, 0.65, 0.69, 0.48, 0.85, 0.78, 0.90, 0.91),
            strict=True,
        )
    ),
    "modeled": dict(
        zip(
            ("avg", *TABLE_CLASSES),
            (0.84, 0.96, 0.84, 0.79, 0.70, 0.79, 0.52, 0.93, 0.90, 0.98, 0.97),
            strict=True,
        )
    ),
}


def paper_value(experiment: str, metric: str, curve: str, x: float) -> float | None:
    """The paper's `metric` of `curve` at `x` in `experiment`'s figure, or None."""
    for px, v in CURVES.get(experiment, {}).get(metric, {}).get(curve, []):
        if px == x:
            return v
    return None
