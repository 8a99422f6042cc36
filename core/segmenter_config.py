"""How a Segmenter runs: one nested configuration, `SegmenterConfig` = pre / grid / crf / post
/ background (plus the mount and the camera check), with every setting's default, bounds,
command-line flag and help declared once on its field (`core.config.setting`). The
command-line options and the services' TOML keys are generated from it
(`services.cli.options`), and `SegmenterConfig.from_dict` reads it from a nested table."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from topseg.core.camera import TopViewMount
from topseg.core.config import from_dict, setting
from topseg.core.crf import CRFConfig
from topseg.core.errors import TopsegError
from topseg.core.resolution import MAX_DOWNSAMPLE

#: Levels of the forest's adaptive grid by default (`GridConfig.adaptive`): one, the grid
#: twice as coarse first; measured in docs/performance.md
ADAPTIVE_LEVELS = 1
#: A walked pixel stops walking trees once its first two (or more) give one class this
#: average posterior (`GridConfig.early_exit`); measured in docs/performance.md. 0.95
#: walks 4 % more nodes than 0.9 and keeps the grid's accuracy loss against full resolution
#: under the accuracy budget's 0.01 on both held-out sets (0.9 lost 0.0106 on one).
EARLY_EXIT = 0.95
#: After the CRF, blobs labelled head smaller than this on the surface (cm2) take their
#: border's label: a fifth of a whole head seen from above (200-300 cm2), so that a head cut
#: by the image's edge mostly keeps its label. On rendered time-of-flight frames it raised
#: the share of head blobs that are heads from 0.31-0.54 to 0.79-0.92 (docs/results.md).
MIN_HEAD_CM2 = 50.0
#: After the CRF, blobs labelled chair, storage or table smaller than this on the surface
#: (cm2) take their border's label: a fifth of a chair's seat seen from above (~1600 cm2).
#: Measured in docs/results.md: avg F1 +0.005 / +0.003 on the held-out sets, furniture on a
#: person 1.1-1.4 points lower on rendered time-of-flight frames.
MIN_FURNITURE_CM2 = 300.0
#: After the CRF, blobs labelled plant smaller than this on the surface (cm2) take their
#: border's label: two thirds of the smallest pot seen from above (14 cm across, ~150 cm2).
#: A noisy camera leaves such specks of plant on table tops. Measured in docs/results.md.
MIN_PLANT_CM2 = 100.0
#: After the CRF, head blobs smaller than this (cm2) whose centre lies within
#: SATELLITE_RADIUS_CM of a larger head blob's take their border's label: an arm or a hand
#: beside a head, as large as a small head (`islands.relabel_islands`). Measured in
#: docs/results.md on rendered time-of-flight frames.
SATELLITE_HEAD_CM2 = 150.0
#: Before labelling, holes without depth inside one surface up to this size (cm2) take the
#: surface's depth (`holes.fill_holes`): a time-of-flight camera's holes in dark hair. On
#: rendered walker frames with hair dropout it took the bundled model's head blobs found
#: from 0.23 to 0.90 at 3.3 m (docs/results.md).
FILL_HOLES_CM2 = 100.0
#: A pixel within this many sigma of the recorded background's noise (plus
#: BACKGROUND_MARGIN_MM) is background without the forest (`BackgroundConfig`)
BACKGROUND_SIGMAS = 3.0
#: ... plus this margin (mm): depth quantisation and a slow drift of the sensor
BACKGROUND_MARGIN_MM = 5.0
#: The worker reports a background that no longer matches when more than this share of its
#: pixels read farther than it (something static went: a fixture or the camera moved)
BACKGROUND_MISMATCH_SHARE = 0.02


def crf_config(mode: str = "realtime") -> CRFConfig:
    """A CRFConfig of `mode` with the default settings."""
    return CRFConfig(mode=mode)


def _area_fields(config: Any) -> list[str]:
    """The names of the fields of `config` that hold an area (cm2): its float fields."""
    return [f.name for f in fields(config) if isinstance(getattr(config, f.name), float | int)]


def _check_areas(config: Any) -> None:
    """Every area field of `config` is finite and >= 0 cm2; TopsegError otherwise."""
    for name in _area_fields(config):
        area = getattr(config, name)
        if not (np.isfinite(area) and area >= 0):
            raise TopsegError(f"{name} must be >= 0 cm2, got {area}")


@dataclass(frozen=True)
class PreConfig:
    """Before labelling: holes without depth up to `fill_holes_cm2` that lie inside one
    surface take its depth (`holes.fill_holes`), so that they are labelled; 0 fills none.
    Models that read raw depth get no pre-processing."""

    fill_holes_cm2: float = setting(
        FILL_HOLES_CM2,
        flag="fill-holes-cm2",
        metavar="A",
        lo=0.0,
        hi=10000.0,
        help="before labelling, holes without depth up to A cm2 that lie inside one surface "
        "(dark hair on a time-of-flight camera) take its depth and its label; 0 leaves them "
        "(default: %(default)s)",
    )

    def __post_init__(self) -> None:
        _check_areas(self)


def _check_switches(config: Any, *names: str) -> None:
    """Each named field of `config` is `on` or `off`; TopsegError otherwise."""
    for name in names:
        if getattr(config, name) not in ("on", "off"):
            raise TopsegError(f"{name} must be on or off, got {getattr(config, name)!r}")


@dataclass(frozen=True)
class GridConfig:
    """The resolution a frame is labelled at and where the forest walks.

    downsample  label every downsample-th pixel of every downsample-th row (forest, CRF and
                island rules at that resolution), the labels brought back to the frame's by
                depth (`resolution`); None: from each frame's mount (`auto_downsample`)
    stride      walk the forest at every stride-th pixel of every stride-th row, the rest
                upsampled by height; None: from each frame's mount (`grid_stride`)
    adaptive    on a grid, levels of coarser grids walked first; 0 walks every grid pixel
    early_exit  a walked pixel stops walking trees once its first two (or more) give one
                class this average posterior; None walks every tree
    context_prior  `on`: the model's context prior folds what each cell is, judged from
                the posteriors up to 75 cm around it, into the posteriors before the CRF
                (`core.context_prior`; a model without one has none); `off`: none
    Models that read raw depth work at their camera's resolution (downsample 1).
    """

    downsample: int | None = setting(
        None,
        flag="downsample",
        metavar="auto|N",
        kind="auto_int",
        lo=1,
        hi=MAX_DOWNSAMPLE,
        help="label every N-th pixel of every N-th row (forest, CRF and blob rules) and give "
        "each pixel the label of its nearest neighbour in depth among them; auto (default) "
        "takes half where a labelled pixel then spans at most 14.4 mm of the floor (a Kinect "
        "v1 up to 4.1 m; 1 for coarser cameras); 1: the frame's own resolution",
    )
    stride: int | None = setting(
        None,
        flag="stride",
        metavar="auto|N",
        kind="auto_int",
        lo=1,
        help="walk the forest at every N-th pixel of every N-th row and upsample the rest by "
        "height; auto (default) spaces walked pixels ~25 mm apart on the floor; 1: every pixel",
    )
    adaptive: int = setting(
        ADAPTIVE_LEVELS,
        flag="adaptive",
        metavar="N",
        kind="int",
        lo=0,
        help="on a grid, walk N coarser grids first and the finer ones only where the coarser "
        "one is unsure or crosses a height edge; 0 walks every grid pixel (default: %(default)s)",
    )
    early_exit: float | None = setting(
        EARLY_EXIT,
        flag="early-exit",
        metavar="P|off",
        kind="share_or_off",
        help="a pixel stops walking trees once its first two (or more) give one class an "
        "average posterior >= P; off walks every tree (default: %(default)s)",
    )
    context_prior: str = setting(
        "on",
        flag="context-prior",
        kind="choice",
        choices=("on", "off"),
        help="before the CRF, the model's context prior (fitted by `topseg person-check`) "
        "judges what each 5 cm cell is (a person, the robot, an object, furniture, "
        "background) from the forest's posteriors up to 75 cm around it and folds that into "
        "the posteriors; off keeps the forest's own (default: %(default)s)",
    )

    def __post_init__(self) -> None:
        if self.stride is not None and (isinstance(self.stride, bool) or self.stride < 1):
            raise TopsegError(f"stride must be >= 1 (or None: from the mount), got {self.stride}")
        if self.downsample is not None and (
            isinstance(self.downsample, bool) or not 1 <= self.downsample <= MAX_DOWNSAMPLE
        ):
            raise TopsegError(
                f"downsample must be 1-{MAX_DOWNSAMPLE} (or None: from the mount), "
                f"got {self.downsample}"
            )
        if isinstance(self.adaptive, bool) or self.adaptive < 0:
            raise TopsegError(f"adaptive must be >= 0 levels, got {self.adaptive}")
        if self.early_exit is not None and not 0.0 < self.early_exit <= 1.0:
            raise TopsegError(f"early_exit must be in (0, 1] (or None), got {self.early_exit}")
        _check_switches(self, "context_prior")


@dataclass(frozen=True)
class PostConfig:
    """After the CRF (realtime or exact, never mode none), blobs too small to be what they
    are labelled take their border's label (`islands.relabel_islands`); 0 keeps them.

    min_head_cm2       head blobs smaller than this on the surface (those at the image's
                       edge under `islands.EDGE_HEAD_SHARE` of it)
    min_furniture_cm2  blobs of chair, storage and table (`islands.FURNITURE_ISLANDS`)
    min_plant_cm2      blobs of plant
    satellite_head_cm2 head blobs smaller than this whose centre lies within
                       `islands.SATELLITE_RADIUS_CM` of a larger head blob's
    person_check       `on`: body-part blobs the model's person check says are not people
                       take their most probable other class (`core.person_check`; a model
                       without a check has none); `off`: none
    surface_vote       `on`: robot and object pixels on one continuous surface take its
                       majority class (`core.surfaces`); `off`: none
    """

    min_head_cm2: float = setting(
        MIN_HEAD_CM2,
        flag="min-head-cm2",
        metavar="A",
        lo=0.0,
        hi=10000.0,
        help="after the CRF, blobs labelled head smaller than A cm2 on the surface (a whole "
        "head seen from above is 200-300) take their border's label, those at the image's "
        "edge (cut by it) under 0.4 A; 0 keeps them (default: %(default)s)",
    )
    min_furniture_cm2: float = setting(
        MIN_FURNITURE_CM2,
        flag="min-furniture-cm2",
        metavar="A",
        lo=0.0,
        hi=100000.0,
        help="the same for blobs labelled chair, storage or table (a chair's seat seen from "
        "above is ~1600 cm2) (default: %(default)s)",
    )
    min_plant_cm2: float = setting(
        MIN_PLANT_CM2,
        flag="min-plant-cm2",
        metavar="A",
        lo=0.0,
        hi=100000.0,
        help="the same for blobs labelled plant (the smallest pot seen from above is ~150 "
        "cm2; a noisy camera leaves specks of plant on table tops) (default: %(default)s)",
    )
    satellite_head_cm2: float = setting(
        SATELLITE_HEAD_CM2,
        flag="satellite-head-cm2",
        metavar="A",
        lo=0.0,
        hi=10000.0,
        help="after the CRF, head blobs smaller than A cm2 whose centre lies within 40 cm of "
        "a larger head blob's (an arm or a hand beside a head) take their border's label; 0 "
        "keeps them (default: %(default)s)",
    )
    person_check: str = setting(
        "on",
        flag="person-check",
        kind="choice",
        choices=("on", "off"),
        help="after the CRF, body-part blobs that the model's person check (fitted by "
        "`topseg person-check`) says are not people, such as the top of a robot link or a "
        "drum, take their most probable other class; off keeps them (default: %(default)s)",
    )
    surface_vote: str = setting(
        "on",
        flag="surface-vote",
        kind="choice",
        choices=("on", "off"),
        help="after the CRF, pixels labelled robot or object that lie on one continuous "
        "surface (neighbours within two sigma of the sensor's depth noise, at least 4 cm) "
        "take the class most of them hold: a large robot link is not a patchwork of robot "
        "and object; off keeps them (default: %(default)s)",
    )

    def __post_init__(self) -> None:
        _check_areas(self)
        _check_switches(self, "person_check", "surface_vote")

    @property
    def any(self) -> bool:
        """Whether some island rule is on (some area above 0)."""
        return max(getattr(self, name) for name in _area_fields(self)) > 0


@dataclass(frozen=True)
class BackgroundConfig:
    """The recorded background of a static cell (`core.background`, `stages.background`).

    path            the background file of `topseg calibrate --background`; None: off
    sigmas          a pixel whose depth lies within this many sigma of the background's
                    noise, plus `margin_mm`, is background without walking the forest
    margin_mm       see `sigmas`
    mismatch_share  the worker reports the background as no longer matching when more than
                    this share of its pixels read farther than it for several frames
    """

    path: str | None = setting(
        None,
        flag="background",
        metavar="FILE|off",
        kind="path",
        help="the static cell's background from `topseg calibrate --background`: pixels "
        "within its noise are background without walking the forest; off (default): none",
    )
    sigmas: float = setting(
        BACKGROUND_SIGMAS,
        flag="background-sigmas",
        metavar="K",
        lo=0.5,
        hi=20.0,
        help="a pixel within K sigma of the background's noise (plus the margin, at most "
        "150 mm) is background (default: %(default)s)",
    )
    margin_mm: float = setting(
        BACKGROUND_MARGIN_MM,
        flag="background-margin-mm",
        metavar="MM",
        lo=0.0,
        hi=100.0,
        help="added to the background's tolerance (default: %(default)s)",
    )
    mismatch_share: float = setting(
        BACKGROUND_MISMATCH_SHARE,
        flag="background-mismatch",
        metavar="P",
        lo=0.001,
        hi=1.0,
        help="the worker reports the background as no longer matching (a fixture or the "
        "camera moved) when more than this share of its pixels read farther than it for "
        "several frames, and labels without it until it matches (default: %(default)s)",
    )

    def __post_init__(self) -> None:
        if self.path is not None and (not isinstance(self.path, str) or not self.path):
            raise TopsegError(f"background must be a file name (or None: off), got {self.path!r}")
        if not (np.isfinite(self.sigmas) and self.sigmas > 0):
            raise TopsegError(f"background sigmas must be > 0, got {self.sigmas}")
        if not (np.isfinite(self.margin_mm) and self.margin_mm >= 0):
            raise TopsegError(f"background margin_mm must be >= 0, got {self.margin_mm}")
        if not 0.0 < self.mismatch_share <= 1.0:
            raise TopsegError(
                f"background mismatch_share must be in (0, 1], got {self.mismatch_share}"
            )


@dataclass(frozen=True)
class SegmenterConfig:
    """How a Segmenter runs: one nested configuration.

    pre           pre-processing (`PreConfig`)
    grid          working resolution and where the forest walks (`GridConfig`)
    crf           the CRF (`crf.CRFConfig`; mode `none` is the forest's argmax)
    post          the island rules after the CRF (`PostConfig`)
    background    the static cell's recorded background (`BackgroundConfig`; off by default)
    mount         the camera's mount, for frames labelled without one of their own (a
                  height model needs one or the other)
    check_camera  a depth model (no heights): refuse frames that do not come from the
                  model's camera (size, focal length); off where frames of other sizes are
                  expected. Height models take any camera.
    """

    pre: PreConfig = field(default_factory=PreConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    crf: CRFConfig = field(default_factory=crf_config)
    post: PostConfig = field(default_factory=PostConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    mount: TopViewMount | None = None
    check_camera: bool = True

    @property
    def relabels_islands(self) -> bool:
        """Whether labels get the island rules after the CRF: some minimum area above 0, and
        a CRF (never in mode none: that is the forest's argmax, as it is)."""
        return self.post.any and self.crf.mode != "none"

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "segmenter config") -> SegmenterConfig:
        """The configuration from a nested table (`pre`, `grid`, `crf`, `post`,
        `background`); unknown or
        mistyped keys are a ConfigError naming them. The mount is not read from a table."""
        return from_dict(cls, d, source)
