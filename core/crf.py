"""Potts CRF over forest posteriors (paper section IV): one energy, two ways to minimise it.

E(x) = sum_p U_p(x_p) + sum_{p~q} w_pq [x_p != x_q]

- U_p(l) = -log(max(P(l | p), eps)): the forest's posterior as a unary, in nats.
- p~q runs over 4-connected pairs of pixels that both have depth; pixels without depth
  (depth == 0) take no part and come out as NO_DEPTH.
- w_pq = smoothness * exp(-(d_p - d_q)^2 / (2 depth_sigma_mm^2)): a Potts weight, cut down
  across depth discontinuities when `depth_sigma_mm` > 0 (0 = the paper's plain Potts).

Modes: `none` (argmax), `exact` (alpha-expansion with gco over the full grid, the paper's
method) and `realtime` (`topseg.core.crf_realtime`: the same energy, minimised by a numba
alpha-expansion on the uncertain band only). Both solvers work on integers: unaries and
weights are multiplied by ENERGY_SCALE and rounded (0.001-nat resolution); reported
energies are always recomputed in float from the labeling by `potts_energy`, the one
definition every mode and test uses. See docs/crf.md.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, fields
from typing import Literal

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.errors import TopsegError

#: Factor from float energies (nats) to the solvers' integer energy terms.
ENERGY_SCALE = 1000.0
#: Largest smoothness accepted: keeps every scaled term far inside int32.
MAX_SMOOTHNESS = 1000.0

Mode = Literal["none", "exact", "realtime"]
MODES: tuple[str, ...] = ("none", "exact", "realtime")


@dataclass(frozen=True)
class CRFConfig:
    """How `segment_crf` smooths a frame; TOML-friendly through `to_dict` / `from_dict`.

    mode            none | exact | realtime
    smoothness      Potts weight per cut 4-neighbour edge, in nats
    depth_sigma_mm  > 0 weights an edge by exp(-dd^2 / 2 sigma^2) of its depth step; 0 = off
    eps             posterior floor before -log (caps a unary at -log(eps))
    confidence      realtime: a pixel whose top posterior reaches this and whose 4
                    neighbours share its argmax is fixed to it
    ring            realtime: free pixels are grown by this many 4-neighbour steps
    cycles          realtime: rounds of expansion moves over all labels; 0 = until none
                    lowers the energy (as `exact`)
    """

    mode: Mode = "realtime"
    smoothness: float = 1.0
    depth_sigma_mm: float = 0.0
    eps: float = 1e-6
    confidence: float = 0.4
    ring: int = 1
    cycles: int = 1

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise TopsegError(f"crf mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if not 0.0 <= self.smoothness <= MAX_SMOOTHNESS:
            raise TopsegError(
                f"crf smoothness must be in [0, {MAX_SMOOTHNESS:g}], got {self.smoothness}"
            )
        if self.depth_sigma_mm < 0:
            raise TopsegError(f"crf depth_sigma_mm must be >= 0, got {self.depth_sigma_mm}")
        if not 0.0 < self.eps < 1.0:
            raise TopsegError(f"crf eps must be in (0, 1), got {self.eps}")
        if not 0.0 <= self.confidence <= 1.0:
            raise TopsegError(f"crf confidence must be in [0, 1], got {self.confidence}")
        if self.ring < 0:
            raise TopsegError(f"crf ring must be >= 0, got {self.ring}")
        if self.cycles < 0:
            raise TopsegError(f"crf cycles must be >= 0 (0 = until converged), got {self.cycles}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> CRFConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise TopsegError(
                f"unknown crf setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
            )
        return cls(**d)


def _check_proba(proba: np.ndarray) -> np.ndarray:
    proba = np.asarray(proba)
    if proba.ndim != 3 or proba.shape[2] != L.NUM_CLASSES:
        raise TopsegError(f"posteriors must be (H, W, {L.NUM_CLASSES}), got shape {proba.shape}")
    if not np.issubdtype(proba.dtype, np.floating):
        raise TopsegError(f"posteriors must be floating point, got {proba.dtype}")
    return proba


def _check_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.shape != shape:
        raise TopsegError(f"depth shape {depth.shape} does not match posteriors {shape}")
    return depth


def unaries_from_posteriors(proba: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """(H, W, C) posteriors -> (H, W, C) float32 unary energies -log(max(p, eps))."""
    proba = _check_proba(proba)
    return -np.log(np.maximum(proba, np.float32(eps)), dtype=np.float32)


def edge_weights(depth: np.ndarray, config: CRFConfig) -> tuple[np.ndarray, np.ndarray]:
    """Potts weights of the 4-connected grid: (horizontal (H, W-1), vertical (H-1, W)).

    Horizontal [i, j] joins (i, j)-(i, j+1), vertical [i, j] joins (i, j)-(i+1, j).
    An edge touching a pixel without depth weighs 0.
    """
    d = np.asarray(depth).astype(np.float32)
    valid = d > 0
    wh = np.full((d.shape[0], d.shape[1] - 1), config.smoothness, np.float32)
    wv = np.full((d.shape[0] - 1, d.shape[1]), config.smoothness, np.float32)
    if config.depth_sigma_mm > 0:
        k = np.float32(-0.5 / config.depth_sigma_mm**2)
        wh *= np.exp(k * (d[:, 1:] - d[:, :-1]) ** 2)
        wv *= np.exp(k * (d[1:, :] - d[:-1, :]) ** 2)
    wh[~(valid[:, 1:] & valid[:, :-1])] = 0.0
    wv[~(valid[1:, :] & valid[:-1, :])] = 0.0
    return wh, wv


def grid_energy(
    labels: np.ndarray, unary: np.ndarray, wh: np.ndarray, wv: np.ndarray, valid: np.ndarray
) -> float:
    """Potts energy of `labels` under explicit unaries and edge weights, in float64."""
    lab = np.where(valid, labels, 0).astype(np.intp)
    u = np.take_along_axis(unary, lab[..., None], axis=2)[..., 0]
    data = float(u[valid].sum(dtype=np.float64))
    cut_h = (lab[:, 1:] != lab[:, :-1]) & valid[:, 1:] & valid[:, :-1]
    cut_v = (lab[1:, :] != lab[:-1, :]) & valid[1:, :] & valid[:-1, :]
    smooth = float(wh[cut_h].sum(dtype=np.float64) + wv[cut_v].sum(dtype=np.float64))
    return data + smooth


def potts_energy(
    labels: np.ndarray,
    proba_or_unaries: np.ndarray,
    depth: np.ndarray,
    config: CRFConfig,
    *,
    kind: Literal["proba", "unary"] = "proba",
) -> float:
    """The CRF energy of a labeling (the one definition; lower is better).

    `proba_or_unaries` is (H, W, C) posteriors (`kind="proba"`, turned into unaries with
    `config.eps`) or ready unaries (`kind="unary"`). Pixels with depth == 0 are left out;
    every other pixel must carry a class id below NUM_CLASSES.
    """
    arr = _check_proba(proba_or_unaries)
    depth = _check_depth(depth, arr.shape[:2])
    labels = np.asarray(labels)
    if labels.shape != arr.shape[:2]:
        raise TopsegError(f"labels shape {labels.shape} does not match posteriors {arr.shape[:2]}")
    valid = depth > 0
    if np.any(labels[valid] >= L.NUM_CLASSES):
        raise TopsegError("labels of pixels with depth must be class ids below NUM_CLASSES")
    if kind == "proba":
        unary = unaries_from_posteriors(arr, config.eps)
    elif kind == "unary":
        unary = arr
    else:
        raise ValueError(f"kind must be 'proba' or 'unary', got {kind!r}")
    wh, wv = edge_weights(depth, config)
    return grid_energy(labels, unary, wh, wv, valid)


def grid_edges(
    wh: np.ndarray, wv: np.ndarray, index: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges (s1 < s2, weight) of the grid between pixels with `index` >= 0 and weight > 0."""
    a = np.concatenate([index[:, :-1].ravel(), index[:-1, :].ravel()])
    b = np.concatenate([index[:, 1:].ravel(), index[1:, :].ravel()])
    w = np.concatenate([wh.ravel(), wv.ravel()])
    keep = (a >= 0) & (b >= 0) & (w > 0)
    return a[keep], b[keep], w[keep]


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


def segment_argmax(proba: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-pixel argmax of the posteriors; NO_DEPTH where there is no depth.

    A numba pass (~1 ms a frame; numpy's argmax over the class axis takes ~13 ms).
    """
    from topseg.core.crf_realtime import argmax_confidence

    return argmax_confidence(np.ascontiguousarray(proba, np.float32), np.asarray(valid))[0]


def segment_crf(proba: np.ndarray, depth_u16: np.ndarray, config: CRFConfig) -> np.ndarray:
    """(H, W) uint8 labels minimising the Potts energy under `config.mode`.

    Pixels with depth == 0 come out NO_DEPTH and take no part in the graph.
    """
    proba = _check_proba(proba)
    depth = _check_depth(depth_u16, proba.shape[:2])
    valid = depth > 0
    if config.mode == "none":
        return segment_argmax(proba, valid)
    if config.mode == "exact":
        wh, wv = edge_weights(depth, config)
        unary = unaries_from_posteriors(proba, config.eps)
        labels = segment_exact(unary, wh, wv, valid)
        # gco minimises the int32-rounded energy; keep the promise in float as well
        argmax = segment_argmax(proba, valid)
        if grid_energy(labels, unary, wh, wv, valid) > grid_energy(argmax, unary, wh, wv, valid):
            return argmax
        return labels
    from topseg.core.crf_realtime import segment_realtime

    return segment_realtime(proba, depth, config)
