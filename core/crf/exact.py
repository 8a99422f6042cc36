"""`exact` mode: alpha-expansion over the full grid with gco (the paper's method)."""

from __future__ import annotations

import functools

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.crf.energy import ENERGY_SCALE, grid_edges


@functools.cache
def _gco_label_setter():
    """A numba loop that sets gco's initial labels through its C API (python: ~0.8 s/frame).

    Not cached on disk: it holds the address of the C function, which changes between
    processes. Returns None where gco's library cannot be reached that way.
    """
    try:
        import ctypes

        from gco import cgco

        fn = ctypes.CDLL(cgco._cgco._name).gcoInitLabelAtSite
        fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
        fn.restype = ctypes.c_int
    except (ImportError, AttributeError, OSError):
        return None

    @numba.njit
    def set_labels(handle, labels):
        for i in range(labels.shape[0]):
            fn(handle, i, labels[i])

    return set_labels


def gco_expansion(
    unary: np.ndarray,
    s1: np.ndarray,
    s2: np.ndarray,
    w: np.ndarray,
    init: np.ndarray | None = None,
    n_iter: int = -1,
) -> np.ndarray:
    """Alpha-expansion (gco) on a general graph with Potts edges; returns int labels.

    `unary` (N, K) float nats, edges s1[i] < s2[i] with float weights w[i]; both are
    scaled by ENERGY_SCALE to gco's int32. gco starts from `init` (default: label 0
    everywhere) and runs expansion cycles until none lowers the energy (or `n_iter`).
    """
    from gco.pygco import GCO

    n, k = unary.shape
    if n == 0:
        return np.zeros(0, np.intp)
    if k == 1:
        return np.zeros(n, np.intp)
    gc = GCO()
    gc.create_general_graph(n, k, energy_is_float=False)
    try:
        gc.set_data_cost(np.rint(unary * ENERGY_SCALE).astype(np.int32))
        wi = np.rint(w * ENERGY_SCALE).astype(np.int32)
        keep = wi > 0
        if keep.any():
            gc.set_all_neighbors(s1[keep], s2[keep], wi[keep])
        gc.set_smooth_cost((1 - np.eye(k)).astype(np.int32))
        if init is not None:
            init = np.ascontiguousarray(init, np.int32)
            setter = _gco_label_setter()
            if setter is not None:
                setter(int(gc.handle), init)
            else:
                for i, label in enumerate(init.tolist()):
                    gc.init_label_at_site(i, label)
        gc.expansion(n_iter)
        return gc.get_labels().astype(np.intp)
    finally:
        gc.destroy_graph()


def segment_exact(
    unary: np.ndarray, wh: np.ndarray, wv: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """Full-grid alpha-expansion (gco) over every pixel with depth, from the argmax.

    Starting from the argmax makes the result's energy no higher than the forest's own
    labeling (expansion only takes moves that lower it); NO_DEPTH where there is no depth.
    """
    index = np.full(valid.shape, -1, np.int64)
    index[valid] = np.arange(int(valid.sum()))
    s1, s2, w = grid_edges(wh, wv, index)
    u = unary[valid]
    sol = gco_expansion(u, s1, s2, w, init=np.argmin(u, axis=1))
    out = np.full(valid.shape, L.NO_DEPTH, np.uint8)
    out[valid] = sol
    return out
