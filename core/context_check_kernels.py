"""The context check's numba kernels over the working frame (`context_check` turns them into
its cells' features). Their numpy references are in `tests/reference.py`
(`cell_channels_reference`, `cell_features_reference`).

A cell is a `cell` x `cell` block of working pixels. Its channels (`CHANNELS` columns):

  0..5   the share of its pixels whose label falls in each of `table`'s six columns (a pixel
         without depth or under the floor gate counts in column BACKGROUND_COLUMN)
  6      the mean height above the floor (m) of its pixels with depth above the floor gate
         and a height (0 without one)
  7..11  the forest's posteriors summed into `posterior_table`'s five columns, averaged over
         its pixels with depth above the floor gate (0 without one)
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: label columns of a cell's channels, then its mean height, then its posterior columns
LABEL_COLUMNS = 6
HEIGHT = LABEL_COLUMNS
POSTERIOR_COLUMNS = 5
CHANNELS = LABEL_COLUMNS + 1 + POSTERIOR_COLUMNS
#: the channel of the mean person posterior (the posterior table's first column)
PERSON_POSTERIOR = HEIGHT + 1
#: the label column a pixel without depth or under the floor gate counts in
BACKGROUND_COLUMN = 5


@numba.njit(cache=True, parallel=True)
def cell_channels(labels, valid, heights_mm, depth, proba, cell, table, posterior_table):
    """(hc, wc, CHANNELS) float32 channels of every whole cell (see the module; heights in
    mm, NaN read as none; `proba` (H, W, classes) the forest's posteriors,
    `posterior_table` (classes, POSTERIOR_COLUMNS)), with the (hc, wc) float64 sum of depth
    and int32 count of its `valid` pixels, and the int32 count of its pixels whose label has
    table[label, 0] (body parts)."""
    hc, wc = labels.shape[0] // cell, labels.shape[1] // cell
    classes = min(proba.shape[2], posterior_table.shape[0])
    chan = np.zeros((hc, wc, CHANNELS), np.float32)
    depth_sum = np.zeros((hc, wc))
    n_valid = np.zeros((hc, wc), np.int32)
    parts = np.zeros((hc, wc), np.int32)
    inv = 1.0 / (cell * cell)
    for i in numba.prange(hc):
        acc = np.zeros(LABEL_COLUMNS)
        post = np.zeros(POSTERIOR_COLUMNS)
        for j in range(wc):
            acc[:] = 0.0
            post[:] = 0.0
            h_sum, h_n = 0.0, 0
            for r in range(i * cell, (i + 1) * cell):
                for c in range(j * cell, (j + 1) * cell):
                    lab = labels[r, c]
                    if table[lab, 0] > 0:
                        parts[i, j] += 1
                    if valid[r, c]:
                        for q in range(LABEL_COLUMNS):
                            acc[q] += table[lab, q]
                        for k in range(classes):
                            p = proba[r, c, k]
                            for q in range(POSTERIOR_COLUMNS):
                                post[q] += p * posterior_table[k, q]
                        h = heights_mm[r, c]
                        if h == h:
                            h_sum += h
                            h_n += 1
                        depth_sum[i, j] += depth[r, c]
                        n_valid[i, j] += 1
                    else:
                        acc[BACKGROUND_COLUMN] += 1.0
            for q in range(LABEL_COLUMNS):
                chan[i, j, q] = acc[q] * inv
            if h_n > 0:
                chan[i, j, HEIGHT] = h_sum / h_n / 1000.0
            if n_valid[i, j] > 0:
                for q in range(POSTERIOR_COLUMNS):
                    chan[i, j, HEIGHT + 1 + q] = post[q] / n_valid[i, j]
    return chan, depth_sum, n_valid, parts


@numba.njit(cache=True)
def _integral(chan):
    hc, wc, nc = chan.shape
    ii = np.zeros((hc + 1, wc + 1, nc))
    for r in range(hc):
        for c in range(wc):
            for q in range(nc):
                ii[r + 1, c + 1, q] = (
                    chan[r, c, q] + ii[r, c + 1, q] + ii[r + 1, c, q] - ii[r, c, q]
                )
    return ii


@numba.njit(cache=True)
def _box_mean(ii, r, c, k, out):
    """The mean channels of the cells within `k` of (r, c), clipped to the grid, into `out`."""
    hc, wc = ii.shape[0] - 1, ii.shape[1] - 1
    r0, r1 = min(max(r - k, 0), hc), min(max(r + k + 1, 0), hc)
    c0, c1 = min(max(c - k, 0), wc), min(max(c + k + 1, 0), wc)
    area = max((r1 - r0) * (c1 - c0), 1)
    for q in range(out.size):
        out[q] = (ii[r1, c1, q] - ii[r0, c1, q] - ii[r1, c0, q] + ii[r0, c0, q]) / area


@numba.njit(cache=True, parallel=True)
def cell_features(chan, cells_per_cm, rows, cols, rings_cm, boxes_cm, sines, cosines):
    """(n, CHANNELS * (2 + 3 * len(rings_cm))) float32 features of the cells (rows[i],
    cols[i]): their own channels; the mean over the 3 x 3 cells around them; then for each
    ring, the mean, max and min over the directions (sines, cosines) of the mean channels of
    a box of half-width boxes_cm / 2 centred rings_cm away, its height taken relative to the
    cell's own. Distances in cm become cells by the cell's own `cells_per_cm`, rounded half
    up; boxes are clipped to the grid."""
    nc = chan.shape[2]
    n, n_rings, n_dirs = rows.size, rings_cm.size, sines.size
    out = np.zeros((n, nc * (2 + 3 * n_rings)), np.float32)
    ii = _integral(chan)
    for i in numba.prange(n):
        box = np.zeros(nc)
        r, c = rows[i], cols[i]
        s = cells_per_cm[r, c]
        for q in range(nc):
            out[i, q] = chan[r, c, q]
        _box_mean(ii, r, c, 1, box)
        for q in range(nc):
            out[i, nc + q] = box[q]
        own_h = chan[r, c, HEIGHT]
        for g in range(n_rings):
            base = nc * (2 + 3 * g)
            k = math.floor(boxes_cm[g] * 0.5 * s + 0.5)
            for q in range(nc):
                out[i, base + q] = 0.0
                out[i, base + nc + q] = -np.inf
                out[i, base + 2 * nc + q] = np.inf
            for d in range(n_dirs):
                rr = r + math.floor(rings_cm[g] * s * sines[d] + 0.5)
                cc = c + math.floor(rings_cm[g] * s * cosines[d] + 0.5)
                _box_mean(ii, rr, cc, k, box)
                box[HEIGHT] -= own_h
                for q in range(nc):
                    out[i, base + q] += box[q] / n_dirs
                    out[i, base + nc + q] = max(out[i, base + nc + q], box[q])
                    out[i, base + 2 * nc + q] = min(out[i, base + 2 * nc + q], box[q])
    return out


@numba.njit(cache=True)
def cells_to_pixels(chosen, labels, cell, allowed_from):
    """(H, W) uint8 image: 1 at each pixel of a cell with chosen[cell] whose label has
    allowed_from[label]; 0 elsewhere."""
    out = np.zeros(labels.shape, np.uint8)
    hc, wc = chosen.shape
    for i in range(hc):
        for j in range(wc):
            if not chosen[i, j]:
                continue
            for r in range(i * cell, (i + 1) * cell):
                for c in range(j * cell, (j + 1) * cell):
                    if allowed_from[labels[r, c]]:
                        out[r, c] = 1
    return out
