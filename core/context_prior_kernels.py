"""The context prior's numba kernel: a cell's group probabilities folded into its pixels'
posteriors (`context_prior` describes the rule). Its numpy reference is
`tests/reference.py` (`fold_prior_reference`)."""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.crf.argmax import summarise_values


@numba.njit(cache=True, parallel=True)
def fold_prior(proba, valid, cell, groups, has_prior, class_group, alpha, eps, amax, pmax, psecond):
    """Fold each cell's group probabilities into its `valid` pixels' posteriors, in place.

    `proba` (H, W, classes) float32; `groups` (hc, wc, G) float32 the cells' group
    probabilities, read where `has_prior` (hc, wc) is True; `class_group` (classes,) int64
    each class's group. In a cell, with m_g the mean over its valid pixels of their
    posterior mass in group g, every class k of a valid pixel is weighted by
    ((groups[g] + eps) / (m_g + eps)) ** alpha, g its group, and the pixel's posteriors
    normalised again; its argmax and top two go into the summary arrays (amax, pmax,
    psecond). `class_group` covers at least the posteriors' classes. Returns how many
    pixels' argmax changed.
    """
    hc, wc = has_prior.shape
    classes = proba.shape[2]
    n_groups = groups.shape[2]
    changed = np.zeros(hc, np.int64)
    for i in numba.prange(hc):
        mass = np.zeros(n_groups)
        weight = np.zeros(classes)
        buf = np.zeros(classes, np.float32)
        for j in range(wc):
            if not has_prior[i, j]:
                continue
            mass[:] = 0.0
            n = 0
            for r in range(i * cell, (i + 1) * cell):
                for c in range(j * cell, (j + 1) * cell):
                    if valid[r, c]:
                        n += 1
                        for k in range(classes):
                            mass[class_group[k]] += proba[r, c, k]
            if n == 0:
                continue
            for k in range(classes):
                g = class_group[k]
                weight[k] = ((groups[i, j, g] + eps) / (mass[g] / n + eps)) ** alpha
            for r in range(i * cell, (i + 1) * cell):
                for c in range(j * cell, (j + 1) * cell):
                    if not valid[r, c]:
                        continue
                    total = 0.0
                    for k in range(classes):
                        p = proba[r, c, k] * weight[k]
                        buf[k] = p
                        total += p
                    if total <= 0.0:
                        continue
                    for k in range(classes):
                        buf[k] = np.float32(buf[k] / total)
                        proba[r, c, k] = buf[k]
                    before = amax[r, c]
                    summarise_values(buf, r, c, amax, pmax, psecond)
                    if amax[r, c] != before:
                        changed[i] += 1
    return changed.sum()
