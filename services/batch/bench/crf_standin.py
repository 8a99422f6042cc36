"""Stand-in scenes and forest-like posteriors for `topseg bench crf --unaries synthetic` and tests.

The CRF needs realistic unaries to be judged: mostly confident floor, furniture and body
parts with errors clustered near boundaries. Without training a forest (which takes the bench
~20 s), these functions draw a top-view scene of a few primitives (a person, furniture,
Kinect shadows) and turn its label map into posteriors by mixing the one-hot truth with
spatially smooth Dirichlet noise, more of it near boundaries, so that argmax is ~85-90 % right
on the foreground and wrong in blobs, as a forest's is. Bench code, not part of the core.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from topseg.core import labels as L
from topseg.core.camera import PAPER_MOUNT

#: the stand-in scene's floor: the paper's mount, as the procedural scenes it imitates
FLOOR_MM = int(PAPER_MOUNT.height_mm)


def _ellipse(shape, cx, cy, ax, ay, angle):
    """Mask of a rotated ellipse centred (cx, cy) with semi-axes (ax, ay) in pixels."""
    v, u = np.indices(shape, dtype=np.float32)
    c, s = np.cos(angle), np.sin(angle)
    x, y = (u - cx) * c + (v - cy) * s, -(u - cx) * s + (v - cy) * c
    return (x / ax) ** 2 + (y / ay) ** 2 <= 1.0


def _rect(shape, cx, cy, hx, hy, angle):
    """Mask of a rotated rectangle centred (cx, cy) with half-sizes (hx, hy) in pixels."""
    v, u = np.indices(shape, dtype=np.float32)
    c, s = np.cos(angle), np.sin(angle)
    x, y = (u - cx) * c + (v - cy) * s, -(u - cx) * s + (v - cy) * c
    return (np.abs(x) <= hx) & (np.abs(y) <= hy)


def _person(shape, rng, cx, cy, angle, sc):
    """(mask, label, depth_mm) primitives of a person seen from above, far to near.

    Sizes are pixels of a 640x480 frame, scaled by `sc`.
    """
    c, s = np.cos(angle), np.sin(angle)

    def at(dx, dy):  # body frame (x across the shoulders, y forward) -> pixels
        return cx + sc * (dx * c - dy * s), cy + sc * (dx * s + dy * c)

    parts = []
    for side in (-1, 1):  # legs peek out beside the torso
        parts.append(
            (_ellipse(shape, *at(side * 18, 12 * side), 14 * sc, 22 * sc, angle), L.LEGS, 2700)
        )
    parts.append((_ellipse(shape, *at(0, 0), 48 * sc, 26 * sc, angle), L.BODY, 2100))
    for side in (-1, 1):
        reach = rng.uniform(0, 1)  # 0: arm down along the body, 1: stretched forward
        sx, sy = side * 44, 0.0
        ex, ey = sx + side * 10, sy + 45 * reach + 10
        wx, wy = ex + side * 4, ey + 45 * reach + 8
        for (ax_, ay_), (bx, by), lab, d in (
            ((sx, sy), (ex, ey), L.UPPER_ARM, 2150),
            ((ex, ey), (wx, wy), L.LOWER_ARM, 2250 - 250 * reach),
        ):
            mx, my = (ax_ + bx) / 2, (ay_ + by) / 2
            half = max(np.hypot(bx - ax_, by - ay_) / 2, 8)
            seg_angle = angle + np.arctan2(by - ay_, bx - ax_)
            parts.append((_rect(shape, *at(mx, my), half * sc, 8 * sc, seg_angle), lab, d))
        hx, hy = wx + side * 2, wy + 10
        parts.append(
            (_ellipse(shape, *at(hx, hy), 10 * sc, 10 * sc, 0.0), L.HAND, 2300 - 300 * reach)
        )
    parts.append((_ellipse(shape, *at(0, 4), 21 * sc, 24 * sc, angle), L.HEAD, 1850))
    return parts


def synthetic_scene(
    rng: np.random.Generator, shape: tuple[int, int] = (480, 640), shadow_px: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """A top-view frame of a person among furniture: (depth uint16 mm, labels uint8).

    Sizes are those of the Kinect v1 at 3.5 m (a table ~250x160 px, a head ~45 px);
    each object casts a `shadow_px` wide strip of no depth on its right, as the
    Kinect's offset projector does.
    """
    h, w = shape
    sc = min(h / 480, w / 640)
    depth = np.full(shape, FLOOR_MM, np.float32)
    labels = np.zeros(shape, np.uint8)
    prims = []
    furniture = (
        (L.TABLE, 2750, (_rect, 125, 80)),
        (L.STORAGE, 2650, (_rect, 60, 40)),
        (L.CHAIR, 3050, (_rect, 40, 40)),
        (L.PLANT, 3150, (_ellipse, 30, 30)),
    )
    for lab, d, (fn, a, b) in furniture:
        if rng.random() < 0.8:
            cx, cy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.9) * h
            prims.append((fn(shape, cx, cy, a * sc, b * sc, rng.uniform(0, np.pi)), lab, d))
    cx, cy = rng.uniform(0.25, 0.75) * w, rng.uniform(0.25, 0.75) * h
    prims += _person(shape, rng, cx, cy, rng.uniform(0, 2 * np.pi), sc)
    occupied = np.zeros(shape, bool)
    for mask, lab, d in prims:  # z-buffer: nearer surfaces win
        nearer = mask & (d < depth)
        depth[nearer] = d
        labels[nearer] = lab
        occupied |= mask
    if shadow_px > 0:
        shifted = np.zeros_like(occupied)
        shifted[:, shadow_px:] = occupied[:, :-shadow_px]
        shadow = shifted & ~occupied
        depth[shadow] = 0
        labels[shadow] = L.NO_DEPTH
    return depth.astype(np.uint16), labels


def boundary_distance(labels: np.ndarray) -> np.ndarray:
    """Euclidean distance (pixels) of every pixel to the nearest label change."""
    edge = np.zeros(labels.shape, bool)
    dh = labels[:, 1:] != labels[:, :-1]
    dv = labels[1:, :] != labels[:-1, :]
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    return ndimage.distance_transform_edt(~edge).astype(np.float32)


def forest_like_posteriors(
    labels: np.ndarray,
    rng: np.random.Generator,
    mix_background: float = 0.2,
    mix_foreground: float = 0.45,
    mix_boundary: float = 0.85,
    boundary_px: float = 4.0,
    blur_px: float = 3.0,
    sharpness: float = 3.0,
    n_classes: int = L.PAPER_NUM_CLASSES,
) -> np.ndarray:
    """(H, W, n_classes) float32 posteriors that look like a forest's on `labels` (class ids
    below `n_classes`: a paper model's eleven by default).

    p = (1 - m) * onehot(truth) + m * D, where D = softmax(`sharpness` * G) of a Gaussian
    field G blurred by `blur_px` and rescaled to unit variance (so mistakes come in
    blobs, each favouring one or two wrong classes), and the mix m
    rises from `mix_background` / `mix_foreground` to `mix_boundary` within ~`boundary_px`
    of a label change. Pixels without depth get a uniform posterior.
    """
    h, w = labels.shape
    c = n_classes
    field = ndimage.gaussian_filter(
        rng.standard_normal((h, w, c), dtype=np.float32), sigma=(blur_px, blur_px, 0)
    )
    field *= sharpness / field.std()
    noise = np.exp(field - field.max(axis=-1, keepdims=True))
    noise /= noise.sum(axis=-1, keepdims=True)
    far = np.where(labels == L.BACKGROUND, mix_background, mix_foreground).astype(np.float32)
    near = np.exp(-boundary_distance(labels) / boundary_px)
    m = (far + (mix_boundary - far) * near)[..., None]
    valid = labels != L.NO_DEPTH
    onehot = np.zeros((h, w, c), np.float32)
    onehot[valid, labels[valid]] = 1.0
    proba = (1.0 - m) * onehot + m * noise
    proba[~valid] = 1.0 / c
    return proba.astype(np.float32)
