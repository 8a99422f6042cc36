"""One surface, one thing (`core.surfaces`): robot and object pixels on one continuous surface
take its majority class. Off with `--surface-vote off`, in CRF mode none (the forest's argmax,
as it is), for a model without both classes, and for a frame without a mount (the sensor's
noise sets the step)."""

from __future__ import annotations

from topseg.core.stages.base import CRFS_SHARE, Stage
from topseg.core.stages.plan import FrameState
from topseg.core.surfaces import surface_step_mm, vote_surfaces, voting_table


class SurfaceVoteStage(Stage):
    """Robot and object labels made one per continuous surface, at the working resolution."""

    name = "surfaces"
    counters = ("surface_votes_px",)
    share = CRFS_SHARE

    def __init__(self, model) -> None:
        super().__init__(model)
        self.voting = voting_table(model.forest.n_classes)

    def run(self, frame: FrameState) -> None:
        """Vote over the surfaces of the smoothed working depth; count the pixels changed."""
        changed = 0
        if self.active(frame):
            step = surface_step_mm(frame.plan.work_mount.sensor)
            changed, _ = vote_surfaces(frame.labels, frame.forest_depth, step, self.voting)
        frame.counts["surface_votes_px"] = changed

    def active(self, frame: FrameState) -> bool:
        """Whether this frame gets the vote."""
        return (
            bool(self.voting.any())
            and self.model.config.post.surface_vote == "on"
            and self.model.config.crf.mode != "none"
            and frame.plan.work_mount is not None
        )
