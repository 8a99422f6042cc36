"""The split criterion: information gain (bits) of thresholds from per-class histograms.

A node's candidate response is binned against its K sorted thresholds (`_bin_histogram`);
the cumulative sums of the (K + 1, C) histogram give the class counts left and right of
every threshold at once, and so the information gain of all K (`_gains_from_histogram`).
"""

from __future__ import annotations

import numba
import numpy as np


def xlogx_table(n: int) -> np.ndarray:
    """(n + 1,) float64 table of i log2 i (0 for i = 0), for counts up to n."""
    i = np.arange(n + 1, dtype=np.float64)
    out = np.zeros(n + 1)
    out[1:] = i[1:] * np.log2(i[1:])
    return out


@numba.njit(cache=True)
def _bin_histogram(resp, y, thresholds, hist):
    """Fill hist (K + 1, C): row b counts samples with exactly b sorted thresholds <= response.

    A sample goes left of threshold k (response < t_k) iff its bin is <= k.
    """
    k = thresholds.shape[0]
    hist[:] = 0
    for i in range(resp.shape[0]):
        v = resp[i]
        lo, hi = 0, k  # bisect right
        while lo < hi:
            mid = (lo + hi) >> 1
            if v < thresholds[mid]:
                hi = mid
            else:
                lo = mid + 1
        b = lo
        hist[b, y[i]] += 1


@numba.njit(cache=True)
def _gains_from_histogram(hist, xlogx, gains):
    """Fill gains (K,) with the information gain (bits) of each threshold from hist (K + 1, C).

    With S(counts) = n log2 n - sum_c n_c log2 n_c (= n H), the gain of a split is
    (S(parent) - S(left) - S(right)) / n; `xlogx[i]` = i log2 i. Only classes present in
    the node are visited.
    """
    k = hist.shape[0] - 1
    n_classes = hist.shape[1]
    total = np.zeros(n_classes, np.int64)
    for b in range(k + 1):
        for c in range(n_classes):
            total[c] += hist[b, c]
    present = np.empty(n_classes, np.int64)
    n_present = 0
    n = 0
    s_parent = 0.0
    for c in range(n_classes):
        if total[c] > 0:
            present[n_present] = c
            n_present += 1
            n += total[c]
            s_parent -= xlogx[total[c]]
    s_parent += xlogx[n]
    left = np.zeros(n_classes, np.int64)
    n_left = 0
    for t in range(k):
        s_left = 0.0
        s_right = 0.0
        for q in range(n_present):
            c = present[q]
            left[c] += hist[t, c]
            n_left += hist[t, c]
            s_left -= xlogx[left[c]]
            s_right -= xlogx[total[c] - left[c]]
        s_left += xlogx[n_left]
        s_right += xlogx[n - n_left]
        gains[t] = (s_parent - s_left - s_right) / n
