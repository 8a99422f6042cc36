"""One way from a depth frame to labels: the forest's posteriors, then the CRF.

A `Segmenter` holds a loaded forest, its model header and the settings that shape a run
(`SegmenterConfig`: the CRF today; a camera mount and speed options are meant to join it
as further fields). Every caller that labels frames (the worker, `segment`, `evaluate`,
experiments, the demo, training's validation split, the benches) goes through it, so
there is one validation of a frame, one argmax and one way to time the two stages.
`bundled_model_path` finds the model shipped with topseg, used when no `--model` is named.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from topseg.core import labels as L
from topseg.core.errors import TopsegError

if TYPE_CHECKING:
    from topseg.core.camera import Intrinsics
    from topseg.core.crf import CRFConfig
    from topseg.core.forest.tree import Forest

# The numba modules (camera, forest, crf) are imported where they are used, so that a
# command's `--help` (which reads MODEL_HELP) does not compile or load them.

#: Where `deploy/install.sh` puts the bundled model (below its --root).
INSTALLED_MODEL = Path("/opt/topseg/models/default.npz")
#: The bundled model inside a checkout, relative to its root.
CHECKOUT_MODEL = Path("models") / "default.npz"
#: Help text for `--model` of every command that defaults to the bundled model.
MODEL_HELP = (
    "model file from `topseg train` (default: the bundled model, models/default.npz of "
    "the checkout, or /opt/topseg/models/default.npz when installed with deploy/install.sh)"
)


def bundled_model_path() -> Path:
    """The bundled model: the checkout's `models/default.npz`, else the installed copy.

    The installed copy is found beside the venv that runs topseg (`install.sh` puts the venv
    at PREFIX/venv and the model at PREFIX/models/), else at /opt/topseg. A TopsegError
    (one line) when there is none.
    """
    candidates = [
        Path(__file__).resolve().parents[1] / CHECKOUT_MODEL,  # core/ -> the checkout root
        Path(sys.prefix).resolve().parent / CHECKOUT_MODEL,  # PREFIX/venv -> PREFIX/models
        INSTALLED_MODEL,
    ]
    for path in candidates:
        if path.is_file():
            return path
    raise TopsegError(
        f"no bundled model (looked for {', '.join(map(str, dict.fromkeys(candidates)))}); "
        "name one with --model"
    )


def model_camera(header: dict | None) -> Intrinsics:
    """The intrinsics the model was trained for (Kinect v1 when the header does not say)."""
    from topseg.core.camera import KINECT_V1, TopViewMount

    cam = (header or {}).get("dataset", {}).get("attrs", {}).get("camera")
    if not cam:
        return KINECT_V1
    try:
        return TopViewMount.from_dict(cam).intrinsics
    except (KeyError, TypeError, ValueError) as exc:
        raise TopsegError(f"the model's header names an unreadable camera ({exc})") from None


def _crf_config(mode: str = "realtime") -> CRFConfig:
    """A CRFConfig of `mode` with the default settings."""
    from topseg.core.crf import CRFConfig

    return CRFConfig(mode=mode)


@dataclass(frozen=True)
class SegmenterConfig:
    """How a Segmenter runs: the seam where run settings are added as fields.

    crf           the CRF settings (mode `none` is the forest's argmax)
    check_camera  refuse frames that do not come from the model's camera (size, focal
                  length); off where frames of other sizes are expected (the worker's tests)
    stride        forest evaluated at every stride-th pixel of every stride-th row (1 = all)
    """

    crf: CRFConfig = field(default_factory=_crf_config)
    check_camera: bool = True
    stride: int = 1

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise TopsegError(f"stride must be >= 1, got {self.stride}")


@dataclass(frozen=True)
class Timings:
    """Milliseconds one frame took: forest, CRF, and the two stages together."""

    forest_ms: float
    crf_ms: float
    total_ms: float


@dataclass(frozen=True)
class Segmentation:
    """What `Segmenter.label` returns for one frame.

    labels   (H, W) uint8 class ids, NO_DEPTH (255) where there is no depth
    proba    (H, W, C) float32 forest posteriors: the Segmenter's reused buffer, valid
             until its next call (copy it to keep it)
    timings  per-stage milliseconds
    """

    labels: np.ndarray
    proba: np.ndarray
    timings: Timings


class Segmenter:
    """A loaded forest and its run settings: `label(depth)` -> labels, posteriors, timings.

    Build it from arrays (`Segmenter(forest, header, crf="realtime")`) or from a model file
    (`Segmenter.from_file(path)`, None = the bundled model). The posterior buffer is reused
    across frames of one size, so one Segmenter serves one thread.
    """

    def __init__(
        self,
        forest: Forest,
        header: dict | None = None,
        config: SegmenterConfig | None = None,
        *,
        crf: CRFConfig | str | None = None,
        model_id: str | None = None,
        path: Path | None = None,
    ) -> None:
        config = config or SegmenterConfig()
        if crf is not None:
            crf = _crf_config(crf) if isinstance(crf, str) else crf
            config = replace(config, crf=crf)
        self.forest = forest
        self.header: dict[str, Any] = dict(header or {})
        self.config = config
        self.path = path
        self.model_id = str(
            model_id or self.header.get("model_id") or (path.name if path else "model")
        )
        self.camera = model_camera(self.header)
        self._out: np.ndarray | None = None

    @classmethod
    def from_file(
        cls,
        path: str | Path | None = None,
        config: SegmenterConfig | None = None,
        *,
        crf: CRFConfig | str | None = None,
    ) -> Segmenter:
        """Load a model file (None: the bundled model). ModelFileError says what is wrong."""
        from topseg.core.forest.model_file import load_model

        path = bundled_model_path() if path is None else Path(path)
        forest, header = load_model(path)
        return cls(forest, header, config, crf=crf, path=path)

    @property
    def crf_config(self) -> CRFConfig:
        """The CRF settings every frame is smoothed with."""
        return self.config.crf

    @property
    def crf_mode(self) -> str:
        """`none`, `exact` or `realtime`."""
        return self.config.crf.mode

    def check_frame(
        self, depth: np.ndarray, intrinsics: Intrinsics | None = None, name: str = "frame"
    ) -> None:
        """The one validation of a frame: the model's camera size and, when the frame says
        its intrinsics, focal length (features are metric offsets scaled by it). TopsegError
        naming the frame."""
        expected = self.camera
        shape = np.shape(depth)
        if shape != expected.shape:
            got = f"{shape[1]}x{shape[0]}" if len(shape) == 2 else f"of shape {shape}"
            raise TopsegError(
                f"{name}: frame is {got} but the model was trained for "
                f"{expected.width}x{expected.height}; resample it to that camera first"
            )
        if intrinsics is not None and abs(intrinsics.fx - expected.fx) > 0.01 * expected.fx:
            raise TopsegError(
                f"{name}: focal length {intrinsics.fx:.1f} px differs from the model's "
                f"{expected.fx:.1f} px"
            )

    def posteriors(self, depth: np.ndarray) -> np.ndarray:
        """The forest stage alone: (H, W, C) float32 posteriors in the reused buffer."""
        from topseg.core.forest.predict import predict_proba

        shape = (*np.shape(depth), L.NUM_CLASSES)
        if self._out is None or self._out.shape != shape:
            self._out = np.empty(shape, np.float32)
        return predict_proba(self.forest, depth, out=self._out, stride=self.config.stride)

    def smooth(self, proba: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """The CRF stage alone: (H, W) uint8 labels of `proba` under this CRF mode."""
        from topseg.core.crf import segment_crf

        return segment_crf(proba, depth, self.config.crf)

    def label(
        self, depth: np.ndarray, intrinsics: Intrinsics | None = None, name: str = "frame"
    ) -> Segmentation:
        """Labels, posteriors and timings of one uint16 depth frame (validated first when
        `config.check_camera`; `name` names it in the error)."""
        if self.config.check_camera:
            self.check_frame(depth, intrinsics, name)
        t0 = time.perf_counter()
        proba = self.posteriors(depth)
        t1 = time.perf_counter()
        labels = self.smooth(proba, depth)
        t2 = time.perf_counter()
        ms = 1000.0
        return Segmentation(labels, proba, Timings(ms * (t1 - t0), ms * (t2 - t1), ms * (t2 - t0)))

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the kernels on a small frame, before the
        first real one; the frame is not checked against the model's camera."""
        depth = np.full((48, 64), 3000, np.uint16)
        self.smooth(self.posteriors(depth), depth)
