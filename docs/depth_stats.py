"""Statistics of a depth frame that describe its sensor, not its scene (for docs/explanation/noise.md).

Used to compare the synthetic Kinect v1 model with real Kinect v1 frames (docs/explanation/noise.md):
how far apart the depth levels are at each depth (disparity quantisation), how rough flat
surfaces are at each depth (noise), how wide the no-depth bands beside depth jumps are and on
which side (projector shadows), how often pixels beside jumps are missing, and how often they
take a depth between the two sides (flying pixels). All take uint16 mm frames, 0 = no depth.

An analysis tool, not part of the package: docs/noise_figure.py imports it from this folder
and tests/test_noise.py checks it.
"""

from __future__ import annotations

import numpy as np


def level_spacing(depth: np.ndarray, edges_mm: np.ndarray) -> np.ndarray:
    """Median gap (mm) between consecutive distinct depth values in each depth bin; NaN where
    a bin holds fewer than 4 levels."""
    levels = np.unique(depth[depth > 0]).astype(np.float64)
    gaps = np.diff(levels)
    mids = (levels[1:] + levels[:-1]) / 2
    out = np.full(len(edges_mm) - 1, np.nan)
    for i in range(len(out)):
        m = (mids >= edges_mm[i]) & (mids < edges_mm[i + 1])
        if m.sum() >= 4:
            out[i] = np.median(gaps[m])
    return out


def roughness(
    depth: np.ndarray, edges_mm: np.ndarray, block: int = 8, max_span_mm: float = 150.0
) -> np.ndarray:
    """Per depth bin, the median standard deviation (mm) of depth about a plane fitted to each
    fully measured `block` x `block` patch whose depth spans less than `max_span_mm`."""
    h, w = depth.shape
    hb, wb = h // block, w // block
    tiles = (
        depth[: hb * block, : wb * block]
        .reshape(hb, block, wb, block)
        .swapaxes(1, 2)
        .reshape(-1, block * block)
    )
    tiles = tiles.astype(np.float64)
    ok = np.all(tiles > 0, axis=1) & (np.ptp(tiles, axis=1) < max_span_mm)
    t = tiles[ok]
    yy, xx = np.mgrid[:block, :block]
    a = np.column_stack([np.ones(block * block), xx.ravel(), yy.ravel()])
    coef, *_ = np.linalg.lstsq(a, t.T, rcond=None)
    resid = t - (a @ coef).T
    sd = resid.std(axis=1) * np.sqrt(block * block / (block * block - 3))
    z = t.mean(axis=1)
    out = np.full(len(edges_mm) - 1, np.nan)
    for i in range(len(out)):
        m = (z >= edges_mm[i]) & (z < edges_mm[i + 1])
        if m.sum() >= 5:
            out[i] = np.median(sd[m])
    return out


def gap_runs(depth: np.ndarray, jump_mm: float = 150.0, max_width: int = 60) -> np.ndarray:
    """No-depth runs along rows between two measured pixels whose depths differ by more than
    `jump_mm`: rows of (width px, near mm, far mm, far_on_left 0/1)."""
    rows = []
    for row in depth:
        missing = row == 0
        d = np.diff(missing.astype(np.int8))
        starts = np.nonzero(d == 1)[0] + 1
        ends = np.nonzero(d == -1)[0] + 1
        for s in starts:
            after = ends[ends > s]
            if len(after) == 0:
                continue
            e = after[0]
            if e - s > max_width:
                continue
            left, right = int(row[s - 1]), int(row[e])
            if abs(left - right) <= jump_mm:
                continue
            rows.append((e - s, min(left, right), max(left, right), int(left > right)))
    return np.array(rows, np.float64).reshape(-1, 4)


def shadow_summary(depth: np.ndarray, fb_px_m: float, jump_mm: float = 150.0) -> dict:
    """Where the no-depth bands beside jumps fall and how wide they are against the disparity
    jump fb (1/z_near - 1/z_far) a projector shadow would have."""
    runs = gap_runs(depth, jump_mm)
    if len(runs) == 0:
        return {"runs": 0}
    predicted = fb_px_m * (1000.0 / runs[:, 1] - 1000.0 / runs[:, 2])
    left = runs[:, 3] == 1
    out = {"runs": len(runs), "far_on_left": float(left.mean())}
    for name, m in (("left", left), ("right", ~left)):
        if m.sum() >= 5:
            out[f"{name}_extra_px"] = float(np.median(runs[m, 0] - predicted[m]))
            varied = np.ptp(runs[m, 0]) > 0 and np.ptp(predicted[m]) > 0
            corr = np.corrcoef(runs[m, 0], predicted[m])[0, 1] if varied else np.nan
            out[f"{name}_corr"] = float(corr)
    return out


def jump_pixels(
    depth: np.ndarray, jump_mm: float = 150.0, gap: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along rows: (left, middle, right) depths of every window of 2*gap+1 pixels whose ends are
    measured and differ by more than `jump_mm`."""
    a = depth[:, : -2 * gap].astype(np.float64)
    m = depth[:, gap:-gap].astype(np.float64)
    b = depth[:, 2 * gap :].astype(np.float64)
    sel = (a > 0) & (b > 0) & (np.abs(a - b) > jump_mm)
    return a[sel], m[sel], b[sel]


def edge_summary(depth: np.ndarray, jump_mm: float = 150.0, gap: int = 2) -> dict:
    """Across jumps (see jump_pixels): how often the middle pixel is missing, and how often it
    is a flying pixel, measured but between the two sides by more than 10 % of the jump."""
    a, m, b = jump_pixels(depth, jump_mm, gap)
    if len(a) == 0:
        return {"jumps": 0}
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    margin = 0.1 * (hi - lo)
    measured = m > 0
    flying = measured & (m > lo + margin) & (m < hi - margin)
    return {
        "jumps": len(a),
        "missing": float((~measured).mean()),
        "flying": float(flying.sum() / max(1, measured.sum())),
    }


def summary(depth: np.ndarray, fb_px_m: float) -> dict:
    """The single-number statistics of a frame."""
    return {
        "no_depth": float((depth == 0).mean()),
        **{f"shadow_{k}": v for k, v in shadow_summary(depth, fb_px_m).items()},
        **{f"edge_{k}": v for k, v in edge_summary(depth).items()},
    }
