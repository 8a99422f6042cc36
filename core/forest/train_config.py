"""How a forest is trained (`TrainConfig`), apart from the training itself (`train`), so that
the tree builder can name it."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from topseg.core.config import from_dict, setting
from topseg.core.forest.feature_config import FeatureConfig

SPLITS = ("linear", "axis")


@dataclass(frozen=True)
class TrainConfig:
    """Forest training parameters; the defaults are the paper's (Sharma et al. 2016, V).

    pixels_per_frame: 2000 keeps the paper's full configuration (F = 1600 frames per tree)
        at 3.2 M samples and 1.9 GB of features per tree, while giving each of the ~5
        classes of a frame a few hundred samples.
    max_split_samples: samples used to choose a split at a node; larger nodes are
        subsampled for the choice (all of their samples are still partitioned). Only the
        top levels of a large tree are affected, and 20 000 samples estimate a gain well.
    min_gain: a split must gain more than this many bits.
    """

    n_trees: int = setting(5, flag="trees", kind="int", lo=1, help="trees in the forest")
    max_depth: int = setting(19, flag="depth", kind="int", lo=0, hi=30, help="maximum tree depth")
    frames_per_tree: int = setting(
        1600, flag="frames-per-tree", kind="int", lo=1, help="bagged frames per tree (F)"
    )
    pixels_per_frame: int = setting(
        2000, flag="pixels-per-frame", kind="int", lo=1, help="sampled pixels per frame"
    )
    n_candidates: int = setting(
        100, flag="responses", kind="int", lo=1, help="candidate responses per node (R)"
    )
    n_thresholds: int = setting(
        100, flag="thresholds", kind="int", lo=1, help="thresholds per candidate (K)"
    )
    split: str = setting(
        "linear", flag="split", kind="choice", choices=SPLITS, help="node split: linear or axis"
    )
    linear_k: int = 2
    min_samples_split: int = 20
    min_gain: float = 0.0
    max_split_samples: int = 20000
    features: FeatureConfig = field(default_factory=FeatureConfig)

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {self.split!r}")
        for name in (
            "n_trees",
            "frames_per_tree",
            "pixels_per_frame",
            "n_candidates",
            "n_thresholds",
            "linear_k",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.max_depth <= 30:
            raise ValueError(f"max_depth must be in [0, 30], got {self.max_depth}")
        if self.min_samples_split < 2:
            raise ValueError(f"min_samples_split must be >= 2, got {self.min_samples_split}")
        if self.max_split_samples < 2:
            raise ValueError(f"max_split_samples must be >= 2, got {self.max_split_samples}")
        if self.min_gain < 0:
            raise ValueError(f"min_gain must be >= 0, got {self.min_gain}")

    @property
    def features_per_node(self) -> int:
        """k: pool features one split combines (1 for axis-aligned splits)."""
        return self.linear_k if self.split == "linear" else 1

    def to_dict(self) -> dict[str, Any]:
        """The config as a plain dict (as model headers hold it; `from_dict` reads it back)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "train config") -> TrainConfig:
        """The config in `d` (`to_dict`'s form, as model headers hold it); a key missing takes
        its default, an unknown or mistyped one is a ConfigError naming it."""
        return from_dict(cls, d, source)


# --- sampling ------------------------------------------------------------------------------
