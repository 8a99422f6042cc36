"""The person check (`core.person_check`): body-part blobs that the model's check says are
not people take their most probable other class. Off without a check in the model, with
`--person-check off`, in CRF mode none (the forest's argmax, as it is) and for a model that
reads raw depth (no heights)."""

from __future__ import annotations

import numpy as np

from topseg.core.person_check import IS_PART, Blobs, blob_features, relabel_blobs
from topseg.core.stages.base import CRFS_SHARE, Stage, StageModel
from topseg.core.stages.plan import FrameState


class PersonCheckStage(Stage):
    """Relabel the body-part blobs that are not people, at the working resolution."""

    name = "person_check"
    counters = ("not_people_blobs", "not_people_px")
    share = CRFS_SHARE

    def run(self, frame: FrameState) -> None:
        """Score every body-part blob of `frame.labels`, relabel the ones that fail."""
        blobs, px = 0, 0
        if self.active(frame):
            blobs, px = check_people(frame, self.model.person_check)
        frame.counts.update(not_people_blobs=blobs, not_people_px=px)

    def active(self, frame: FrameState) -> bool:
        """Whether this frame gets the check."""
        return self.model.person_check is not None and checks_run(self.model, frame)


def checks_run(model: StageModel, frame: FrameState) -> bool:
    """Whether the model's checks (context and person) run on `frame`, when the model has
    them: switched on, after a CRF, on a frame with a mount (heights)."""
    return (
        model.config.post.person_check == "on"
        and model.config.crf.mode != "none"
        and frame.plan.work_mount is not None
    )


def check_people(frame: FrameState, check) -> tuple[int, int]:
    """Run `check` over `frame` after its CRF: (blobs, pixels) relabelled."""
    found = frame_blobs(frame)
    if found is None:
        return 0, 0
    blobs, proba = found
    return relabel_blobs(frame.labels, blobs, check.people(blobs), proba)


def frame_blobs(frame: FrameState) -> tuple[Blobs, np.ndarray] | None:
    """The body-part blobs of `frame` after its CRF with their features (what the check
    scores and what `topseg person-check` fits it on), and the posteriors, stored at least
    at every body-part pixel; None without a body-part pixel."""
    human = IS_PART[frame.labels]
    if not human.any():
        return None
    mount = frame.plan.work_mount
    proba = frame.fill(human)
    heights = frame.heights()
    blobs = blob_features(
        frame.labels, frame.depth, heights, proba, mount.intrinsics, mount.height_mm, human
    )
    return blobs, proba
