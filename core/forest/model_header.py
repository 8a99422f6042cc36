"""What a model file's header says about how the model reads frames: the camera a depth
model was trained for (`model_camera`) and a height model's features (`model_features`)."""

from __future__ import annotations

from topseg.core.camera import KINECT_V1, Intrinsics, TopViewMount
from topseg.core.errors import TopsegError
from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.inputs import reads_height
from topseg.core.forest.tree import Forest


def model_camera(header: dict | None) -> Intrinsics:
    """The intrinsics the model was trained for (Kinect v1 when the header does not say)."""
    dataset = (header or {}).get("dataset", {})
    attrs = dataset.get("attrs", {}) if isinstance(dataset, dict) else None
    if not isinstance(attrs, dict):
        raise TopsegError("the model's header names an unreadable dataset (not a table)")
    cam = attrs.get("camera")
    if cam is None or cam == {}:
        return KINECT_V1
    try:
        return TopViewMount.from_dict(cam, source="the model's camera").intrinsics
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise TopsegError(f"the model's header names an unreadable camera ({exc})") from None


def model_features(header: dict | None, forest: Forest | None = None) -> FeatureConfig | None:
    """The FeatureConfig of a model that reads heights (header `"input": "height"`), None for
    one that reads depth. TopsegError when the header says heights but not its features."""
    if not reads_height(header):
        return None
    d = (header or {}).get("features")
    if d is None:
        d = (header or {}).get("recipe", {}).get("config", {}).get("features")
    if not isinstance(d, dict):
        raise TopsegError("the model reads heights but its header does not say its features")
    for key in ("off_image", "edge_gaps"):  # a header without the key: its probes read background
        d = d if key in d else {**d, key: "background"}
    try:
        features = FeatureConfig.from_dict(d, source="the model's feature config")
    except ValueError as exc:
        raise TopsegError(f"the model's header names unreadable features ({exc})") from None
    if forest is not None and features.background_mm != forest.background_mm:
        raise TopsegError("the model's header and forest disagree on background_mm")
    return features
