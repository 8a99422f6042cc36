"""Whether a camera's frames still match the static cell's recorded background.

Each frame the Segmenter counts the background's pixels it saw *farther* than the background
(`background_missing_px`): something static went, which only a moved fixture or a moved
camera does (a person or a robot in the way is nearer, never farther). When that share of the
background's pixels exceeds the mismatch share (`BackgroundConfig.mismatch_share`) for
`MISMATCH_FRAMES` frames in a row, the background no longer matches: the worker says so once
(a warning, its stats and `topseg status`) and labels without it, every pixel through the
forest, until the share stays under the mismatch share for `MATCH_FRAMES` frames in a row;
that is said once too. A gate that no longer matches the cell could send a person who stands
where a fixture was to background; labelling without it fails towards the forest.
"""

from __future__ import annotations

from dataclasses import dataclass

from topseg.core.segmenter_config import BackgroundConfig

#: frames in a row over the mismatch share before the background counts as no longer matching
MISMATCH_FRAMES = 10
#: frames in a row under it before it counts as matching again
MATCH_FRAMES = 10
MATCH, MISMATCH = "match", "mismatch"


@dataclass
class BackgroundWatch:
    """One camera's verdict on its recorded background (see the module)."""

    background_id: str
    config: BackgroundConfig
    state: str = MATCH
    run: int = 0  # frames in a row that disagree with `state`
    mismatches: int = 0  # times the background stopped matching
    missing_share: float = 0.0  # the last frame's
    worst_share: float = 0.0  # the largest share in the current run

    @property
    def gate(self) -> bool:
        """Whether frames are gated with the background (it matches)."""
        return self.state == MATCH

    def note(self, missing_share: float) -> str | None:
        """Take one frame's missing share; the new state when it changes (else None)."""
        self.missing_share = missing_share
        over = missing_share > self.config.mismatch_share
        if over == (self.state == MISMATCH):
            self.run, self.worst_share = 0, 0.0
            return None
        self.run += 1
        self.worst_share = max(self.worst_share, missing_share)
        if self.run < (MISMATCH_FRAMES if over else MATCH_FRAMES):
            return None
        self.state = MISMATCH if over else MATCH
        self.mismatches += over
        self.run = 0
        return self.state

    def stats(self) -> dict:
        """The `background` map of the worker's stats (`wire.encode_stats`)."""
        cfg = self.config
        return {
            "id": self.background_id,
            "state": self.state,
            "missing_share": min(1.0, max(0.0, float(self.missing_share))),
            "mismatch_share": cfg.mismatch_share,
            "sigmas": cfg.sigmas,
            "margin_mm": cfg.margin_mm,
            "mismatches": self.mismatches,
        }
