"""An earlier frame's labels carried onto a newer depth frame of the same camera.

The safety service decides on every depth frame as it arrives, without waiting for the
worker's labels of that frame (which come a frame or more later): its geometry is the new
frame's, and what each pixel is comes from the newest labels the worker sent, carried over
by `carry_labels`. A pixel keeps its earlier label where nothing new appeared on it. A pixel
where something stands nearer the camera than it did then (by more than `APPEARED_MM` and
than the sensor's noise allows, above the floor) is taken as a person's: of the part of the
nearest body-part pixel within `PART_REACH_M` (a hand reaching on, a leg stepping forward),
or of unknown part (`UNIDENTIFIED`) where there is none. A person walking or reaching in is
one the moment the depth shows it, and the labels of the next frames say what it was. The
decision therefore fails towards `stop` while labels lag, never towards `clear`.

Every other pixel keeps its label, a robot label too: with the robot posed by its joint state
the monitor judges robot labels outside the robot's silhouette as it does a frame's own (a
person read as robot is a person when their heights span enough; what a moving link uncovered,
a table or the floor, is flat and is not).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from topseg.core.person_check import IS_PART

#: A pseudo-label for a pixel where something appeared since the labels were made: counted
#: as a person's, of a part without body-region limits (the strictest: `decision._contact`
#: stops the cell for it). Outside the label table, so it is never published as a class.
UNIDENTIFIED = 250
#: A pixel nearer the camera than in the labels' frame by this much (mm), and by
#: APPEARED_SIGMAS times the noise of the difference of two frames, holds something new.
APPEARED_MM = 60
APPEARED_SIGMAS = 4.0
#: ... when it stands at least this high (m) above the floor (not the floor's own noise).
APPEARED_FLOOR_M = 0.05
#: Something that appeared within this (m, measured on the floor) of a body-part
#: pixel is of that part: a person at 1.6 m/s moves 13 cm in the 80 ms labels typically lag.
PART_REACH_M = 0.15


def carry_labels(
    labels: np.ndarray,
    labels_depth_mm: np.ndarray,
    depth_mm: np.ndarray,
    heights_m: np.ndarray,
    pixels_per_m: float,
    noise_mm: np.ndarray | float = 0.0,
) -> np.ndarray:
    """(H, W) uint8: `labels`, made on a frame of depth `labels_depth_mm`, carried onto the
    newer frame `depth_mm` (both axis depth, mm, 0 = none; `heights_m` the newer frame's
    heights above the floor; `pixels_per_m` pixels a metre spans at the frame's depth;
    `noise_mm` one frame's depth noise, 1 sigma, per pixel or one for all). Where something
    appeared (nearer by more than APPEARED_MM and APPEARED_SIGMAS sigma of the difference,
    higher than APPEARED_FLOOR_M; a pixel without depth then never counts) and the label was
    not a person's: the part of the nearest body-part pixel within PART_REACH_M, else
    `UNIDENTIFIED`. The earlier label elsewhere."""
    if not (labels.shape == labels_depth_mm.shape == depth_mm.shape == heights_m.shape):
        raise ValueError(
            f"labels {labels.shape}, their depth {labels_depth_mm.shape}, the new depth "
            f"{depth_mm.shape} and its heights {heights_m.shape} differ"
        )
    old = labels_depth_mm.astype(np.float32)
    new = depth_mm.astype(np.float32)
    step = np.maximum(APPEARED_MM, APPEARED_SIGMAS * np.sqrt(2.0) * np.asarray(noise_mm))
    has_new = new > 0
    # a pixel without depth then (a shadow, a dark surface: they flicker) says nothing new
    appeared = has_new & (old > 0) & (new < old - step) & (heights_m > APPEARED_FLOOR_M)
    out = labels.copy()
    human = IS_PART[labels]
    new_thing = appeared & ~human
    out[new_thing] = UNIDENTIFIED
    reach_px = PART_REACH_M * pixels_per_m
    if reach_px >= 1 and new_thing.any() and human.any():
        distance, (rows, cols) = ndimage.distance_transform_edt(~human, return_indices=True)
        near = new_thing & (distance <= reach_px)
        out[near] = labels[rows[near], cols[near]]
    return out
