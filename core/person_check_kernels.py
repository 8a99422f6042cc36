"""The person check's per-blob sums, one numba pass each over the working frame
(`person_check.blob_features` turns them into features). Their numpy reference is
`tests/test_person_check.py::reference_features`.

Columns of `blob_sums`' output, per blob:

  AREA, AREA_H, AREA_HH    sum of a, a*h, a*h^2 (a: the pixel's area in cm2, h: its height
                           above the floor in mm, 0 without depth)
  PIXELS                   pixels
  H_MAX, H_MIN             highest and lowest h of its pixels with depth (-inf / inf: none)
  PART + i                 area labelled the i-th body part
  HEAD_AREA_H              sum of a*h over its head pixels
  MX, MY, MXX, MYY, MXY    area-weighted moments of its points on the camera's x, y (m)
  TOP                      area within `top_mm` of H_MAX (filled by `blob_top`)
  POSTERIOR + c            sum of the forest's posterior of class c over its pixels
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.union_find import find_root

AREA, AREA_H, AREA_HH, PIXELS, H_MAX, H_MIN = 0, 1, 2, 3, 4, 5
PART = 6  # six body parts: 6..11
HEAD_AREA_H = 12
MX, MY, MXX, MYY, MXY = 13, 14, 15, 16, 17
TOP = 18
POSTERIOR = 19

#: `kinds` table values (`ring_sums`, `component_sums`): what a label is to the check
OTHER, ROBOT, OBJECT, FURNITURE, BACKGROUND = 0, 1, 2, 3, 4
#: columns of `ring_sums`' output
R_PIXELS, R_ROBOT, R_OBJECT, R_FURNITURE, R_BACKGROUND, R_NO_DEPTH = 0, 1, 2, 3, 4, 5
R_VALID, R_H, R_H_MAX, R_TALL = 6, 7, 8, 9
RING_COLUMNS = 10
#: columns of `component_sums`' output
C_AREA, C_ROBOT, C_OBJECT, C_FURNITURE = 0, 1, 2, 3


@numba.njit(cache=True)
def label8(mask):
    """(image, n): the 8-connected components of a bool `mask`, numbered 1..n in the raster
    order of their first pixel (as scipy.ndimage.label numbers them); 0 outside."""
    rows, cols = mask.shape
    image = np.zeros((rows, cols), np.int32)
    parent = np.zeros(rows * cols + 1, np.int32)
    count = 0
    for r in range(rows):
        for c in range(cols):
            if not mask[r, c]:
                continue
            best = 0
            for i, j in ((r - 1, c - 1), (r - 1, c), (r - 1, c + 1), (r, c - 1)):
                if i < 0 or j < 0 or j >= cols or image[i, j] == 0:
                    continue
                root = find_root(parent, image[i, j])
                if best == 0:
                    best = root
                elif root != best:
                    low, high = min(root, best), max(root, best)
                    parent[high] = low
                    best = low
            if best == 0:
                count += 1
                parent[count] = count
                best = count
            image[r, c] = best
    number = np.zeros(count + 1, np.int32)
    n = 0
    for r in range(rows):
        for c in range(cols):
            if image[r, c] == 0:
                continue
            root = find_root(parent, image[r, c])
            if number[root] == 0:
                n += 1
                number[root] = n
            image[r, c] = number[root]
    return image, n


@numba.njit(cache=True)
def _pixel_area(d, fx, fy):
    """A pixel's footprint (cm2) on a surface facing the camera at depth `d` (mm)."""
    return (d / 10.0) * (d / 10.0) / (fx * fy)


@numba.njit(cache=True)
def _height(depth, heights, r, c):
    """A pixel's height (mm; 0 without depth or height)."""
    if depth[r, c] == 0:
        return 0.0
    h = heights[r, c]
    return 0.0 if np.isnan(h) else np.float64(h)


@numba.njit(cache=True)
def blob_sums(image, n, labels, part_of, depth, heights, proba, columns, fx, fy, cx, cy):
    """(n, POSTERIOR + columns) float64 sums per blob of `image` (1..n; 0: none) (module
    docstring); `part_of[label]` is the body part's index 0..5, or -1."""
    out = np.zeros((n, POSTERIOR + columns))
    for k in range(n):
        out[k, H_MAX] = -np.inf
        out[k, H_MIN] = np.inf
    rows, cols = image.shape
    n_proba = min(proba.shape[2], columns)
    for r in range(rows):
        for c in range(cols):
            b = image[r, c]
            if b == 0:
                continue
            k = b - 1
            d = np.float64(depth[r, c])
            a = _pixel_area(d, fx, fy)
            h = _height(depth, heights, r, c)
            out[k, AREA] += a
            out[k, AREA_H] += a * h
            out[k, AREA_HH] += a * h * h
            out[k, PIXELS] += 1.0
            if d > 0:
                out[k, H_MAX] = max(out[k, H_MAX], h)
                out[k, H_MIN] = min(out[k, H_MIN], h)
            part = part_of[labels[r, c]]
            if part >= 0:
                out[k, PART + part] += a
                if part == 0:
                    out[k, HEAD_AREA_H] += a * h
            z = d / 1000.0
            x = (c - cx) * z / fx
            y = (r - cy) * z / fy
            out[k, MX] += a * x
            out[k, MY] += a * y
            out[k, MXX] += a * x * x
            out[k, MYY] += a * y * y
            out[k, MXY] += a * x * y
            for j in range(n_proba):
                out[k, POSTERIOR + j] += proba[r, c, j]
    return out


@numba.njit(cache=True)
def blob_top(image, depth, heights, h_max, top_mm, fx, fy, out):
    """Add to out[k, TOP] the area of blob k's pixels higher than h_max[k] - top_mm."""
    rows, cols = image.shape
    for r in range(rows):
        for c in range(cols):
            b = image[r, c]
            if b == 0:
                continue
            d = np.float64(depth[r, c])
            if _height(depth, heights, r, c) > h_max[b - 1] - top_mm:
                out[b - 1, TOP] += _pixel_area(d, fx, fy)


@numba.njit(cache=True)
def grown(image, radius):
    """The largest blob number within `radius` pixels (a square window, clipped to the
    image) of every pixel outside the blobs. Painted from each blob's edge pixels (those
    with a neighbour outside it, or on the image's edge): a pixel outside a blob within
    `radius` of any of its pixels is within `radius` of one of its edge pixels."""
    rows, cols = image.shape
    out = np.zeros_like(image)
    for r in range(rows):
        for c in range(cols):
            b = image[r, c]
            if b == 0:
                continue
            inner = 0 < r < rows - 1 and 0 < c < cols - 1
            if inner:
                for i in range(r - 1, r + 2):
                    for j in range(c - 1, c + 2):
                        if image[i, j] != b:
                            inner = False
            if inner:
                continue
            for i in range(max(r - radius, 0), min(r + radius + 1, rows)):
                for j in range(max(c - radius, 0), min(c + radius + 1, cols)):
                    if out[i, j] < b:
                        out[i, j] = b
    return out


@numba.njit(cache=True)
def ring_sums(image, n, labels, kinds, depth, heights, radius, tall_mm):
    """(n, RING_COLUMNS) sums over each blob's ring: pixels outside every blob whose window
    of `radius` reaches it, each given to the highest-numbered blob that does. Counts of
    each kind of label (`kinds[label]`), of pixels without depth, and over those with depth
    their heights, highest and how many are above `tall_mm`."""
    around = grown(image, radius)
    out = np.zeros((n, RING_COLUMNS))
    for k in range(n):
        out[k, R_H_MAX] = -np.inf
    rows, cols = image.shape
    for r in range(rows):
        for c in range(cols):
            b = around[r, c]
            if b == 0 or image[r, c] != 0:
                continue
            k = b - 1
            out[k, R_PIXELS] += 1.0
            kind = kinds[labels[r, c]]
            if kind != OTHER:
                out[k, kind] += 1.0
            if depth[r, c] == 0:
                out[k, R_NO_DEPTH] += 1.0
                continue
            h = _height(depth, heights, r, c)
            out[k, R_VALID] += 1.0
            out[k, R_H] += h
            out[k, R_H_MAX] = max(out[k, R_H_MAX], h)
            if h > tall_mm:
                out[k, R_TALL] += 1.0
    return out


@numba.njit(cache=True)
def component_sums(comp, m, image, n, labels, kinds, depth, fx, fy):
    """((m + 1, 4) area sums per foreground component: all, robot, object, furniture;
    (n,) the component of each blob: the highest component number among its pixels)."""
    sums = np.zeros((m + 1, 4))
    which = np.zeros(n, np.int64)
    rows, cols = comp.shape
    for r in range(rows):
        for c in range(cols):
            q = comp[r, c]
            b = image[r, c]
            if b > 0:
                which[b - 1] = max(which[b - 1], q)
            if q == 0:
                continue
            d = np.float64(depth[r, c])
            a = _pixel_area(d, fx, fy)
            sums[q, C_AREA] += a
            kind = kinds[labels[r, c]]
            if kind == ROBOT:
                sums[q, C_ROBOT] += a
            elif kind == OBJECT:
                sums[q, C_OBJECT] += a
            elif kind == FURNITURE:
                sums[q, C_FURNITURE] += a
    return sums, which


#: rows that walk a tree together in `grouped_tree_sums`
ROW_BLOCK = 8


@numba.njit(cache=True, parallel=True)
def grouped_tree_sums(x, feature, threshold, value, group, groups):
    """(n, groups) for each row of `x`, the sum over the trees of each group of the leaf value
    it reaches. The trees are laid out complete, all of one depth D
    (`person_check.complete_trees`): tree t's node k, of (T, 2**D - 1) `feature` and
    `threshold`, sends a row with x[feature] <= threshold to node 2k + 1 and the rest (NaN
    too) to 2k + 2; leaf k of (T, 2**D) `value` ends a walk at node 2**D - 1 + k, and tree t's
    leaf value is summed into column group[t], in tree order.

    No branch on the comparison: the walk's next node is arithmetic on it, so a row costs the
    same whichever way it goes (3.5x faster than walking linked nodes). Rows walk in blocks
    of ROW_BLOCK, all down one tree before the next, so a tree's nodes are read once a block
    rather than once a row (the context prior's five groups of 100 trees of depth 6 on 900
    cells: 6.2 against 9.1 ms a row at a time)."""
    n = x.shape[0]
    trees, inner = feature.shape
    out = np.zeros((n, groups))
    for block in numba.prange((n + ROW_BLOCK - 1) // ROW_BLOCK):
        lo = block * ROW_BLOCK
        rows = min(lo + ROW_BLOCK, n) - lo
        node = np.zeros(ROW_BLOCK, np.int64)
        for t in range(trees):
            node[:] = 0
            while node[0] < inner:  # complete: every row reaches a leaf at the same depth
                for b in range(rows):
                    k = node[b]
                    node[b] = 2 * k + 2 - (x[lo + b, feature[t, k]] <= threshold[t, k])
            g = group[t]
            for b in range(rows):
                out[lo + b, g] += value[t, node[b] - inner]
    return out


@numba.njit(cache=True)
def relabel_rejected(labels, image, is_rejected, proba, allowed):
    """Give each pixel of a blob with is_rejected[blob] its most probable class among
    `allowed` (the first on ties), in place; how many pixels changed label."""
    rows, cols = labels.shape
    classes = min(proba.shape[2], allowed.size)
    count = 0
    for r in range(rows):
        for c in range(cols):
            if not is_rejected[image[r, c]]:
                continue
            best, best_p = -1, -1.0
            for j in range(classes):
                if allowed[j] and proba[r, c, j] > best_p:
                    best, best_p = j, proba[r, c, j]
            labels[r, c] = best
            count += 1
    return count
