"""The Potts energy of a labelling and the settings that shape it (the one definition that every
CRF mode and test uses; see the package docstring)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import numba
import numpy as np

from topseg.core import labels as L
from topseg.core.config import from_dict, setting
from topseg.core.errors import TopsegError

#: Factor from float energies (nats) to the solvers' integer energy terms.
ENERGY_SCALE = 1000.0
#: Largest smoothness accepted: keeps every scaled term far inside int32.
MAX_SMOOTHNESS = 1000.0
#: The Potts weight CRFConfig defaults to (nats per cut edge). On validation frames 3 scores
#: ~0.015 avg F1 higher, but costs the realtime CRF ~2 ms a frame that the 30 fps budget does
#: not have (docs/explanation/crf.md; `--smoothness` chooses per command)
DEFAULT_SMOOTHNESS = 1.0
#: The Potts weight CRFConfig defaults to for frames from a noisy camera (`denoise.needs_denoise`:
#: 20 mm or more of depth noise at the floor, a stereo camera at range), never below
#: `smoothness`: their posteriors are noisier, and on the mounts table (300 frames a cell) 3 nats
#: lifted every stereo cell by 0.003-0.009 avg F1 for ~2.5-3.3 ms of CRF p50 on those cameras
#: only (docs/explanation/crf.md, docs/results.md)
NOISY_SMOOTHNESS = 3.0

Mode = Literal["none", "exact", "realtime"]
MODES: tuple[str, ...] = ("none", "exact", "realtime")


@dataclass(frozen=True)
class CRFConfig:
    """How `segment_crf` smooths a frame; TOML-friendly through `to_dict` / `from_dict`.

    mode            none | exact | realtime
    smoothness      Potts weight per cut 4-neighbour edge, in nats
    noisy_smoothness  the weight for frames from a noisy camera (the Segmenter's
                    `stages.readers.noisy_crf`: those it smooths, `denoise.needs_denoise`), when larger
    depth_sigma_mm  > 0 weights an edge by exp(-dd^2 / 2 sigma^2) of its depth step; 0 = off
    eps             posterior floor before -log (caps a unary at -log(eps))
    confidence      realtime: a pixel whose top posterior reaches this and whose 4
                    neighbours share its argmax is fixed to it
    ring            realtime: free pixels are grown by this many 4-neighbour steps
    cycles          realtime: rounds of expansion moves over all labels; 0 = until none
                    lowers the energy (as `exact`)
    """

    mode: Mode = setting(
        "realtime",
        flag="crf",
        kind="choice",
        choices=MODES,
        help="CRF smoothing after the forest (default: %(default)s)",
    )
    smoothness: float = setting(
        DEFAULT_SMOOTHNESS,
        flag="smoothness",
        metavar="S",
        lo=0.0,
        hi=MAX_SMOOTHNESS,
        help="the CRF's Potts weight per cut edge, in nats (default: %(default)s; 3 scores "
        "~0.015 avg F1 higher and costs the realtime CRF ~2 ms a frame: docs/explanation/crf.md)",
    )
    noisy_smoothness: float = setting(
        NOISY_SMOOTHNESS,
        flag="noisy-smoothness",
        metavar="S",
        lo=0.0,
        hi=MAX_SMOOTHNESS,
        help="the Potts weight for frames from a noisy camera (20 mm or more of depth noise "
        "at the floor, a stereo camera at range: the frames topseg smooths), when larger "
        "than --smoothness (default: %(default)s: docs/explanation/crf.md)",
    )
    depth_sigma_mm: float = 0.0
    eps: float = 1e-6
    confidence: float = 0.4
    ring: int = 1
    cycles: int = 1

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise TopsegError(f"crf mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for name in ("smoothness", "noisy_smoothness"):
            value = getattr(self, name)
            if not 0.0 <= value <= MAX_SMOOTHNESS:
                raise TopsegError(f"crf {name} must be in [0, {MAX_SMOOTHNESS:g}], got {value}")
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
        """The settings as a flat dict (a TOML table, a bench record); `from_dict` reads it back."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "crf settings") -> CRFConfig:
        """The settings in `d` (a TOML table); ConfigError naming an unknown or mistyped key."""
        return from_dict(cls, d, source)


def check_proba(proba: np.ndarray) -> np.ndarray:
    """(H, W, C) floating posteriors over a model's C classes (2 <= C <= NUM_CLASSES), or a
    TopsegError that says what is wrong."""
    proba = np.asarray(proba)
    if proba.ndim != 3 or not 2 <= proba.shape[2] <= L.NUM_CLASSES:
        raise TopsegError(
            f"posteriors must be (H, W, C) with 2 <= C <= {L.NUM_CLASSES} classes, "
            f"got shape {proba.shape}"
        )
    if not np.issubdtype(proba.dtype, np.floating):
        raise TopsegError(f"posteriors must be floating point, got {proba.dtype}")
    return proba


def check_depth_shape(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """`depth` as an array of the posteriors' (H, W), or a TopsegError."""
    depth = np.asarray(depth)
    if depth.shape != shape:
        raise TopsegError(f"depth shape {depth.shape} does not match posteriors {shape}")
    return depth


def unaries_from_posteriors(proba: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """(H, W, C) posteriors -> (H, W, C) float32 unary energies -log(max(p, eps))."""
    proba = check_proba(proba)
    return -np.log(np.maximum(proba, np.float32(eps)), dtype=np.float32)


def edge_weights(depth: np.ndarray, config: CRFConfig) -> tuple[np.ndarray, np.ndarray]:
    """Potts weights of the 4-connected grid: (horizontal (H, W-1), vertical (H-1, W)).

    Horizontal [i, j] joins (i, j)-(i, j+1), vertical [i, j] joins (i, j)-(i+1, j).
    An edge touching a pixel without depth weighs 0; with `depth_sigma_mm` > 0 an edge
    across a depth step d weighs smoothness * exp(-d^2 / (2 sigma^2)) (float32). One numba
    pass over the frame (numpy took six, ~0.5 ms a 640x480 frame).
    """
    d = np.ascontiguousarray(depth)
    h, w = d.shape
    wh = np.empty((h, max(w - 1, 0)), np.float32)
    wv = np.empty((max(h - 1, 0), w), np.float32)
    k = np.float32(-0.5 / config.depth_sigma_mm**2) if config.depth_sigma_mm > 0 else 0.0
    _edge_weights(d, np.float32(config.smoothness), np.float32(k), wh, wv)
    return wh, wv


@numba.njit(cache=True, inline="always")
def _edge_weight(a, b, smoothness, k):
    """The weight of the edge between depths a and b (mm): 0 when either is 0."""
    if a == 0 or b == 0:
        return np.float32(0.0)
    step = np.float32(a) - np.float32(b)
    return smoothness * np.exp(k * (step * step))


@numba.njit(cache=True)
def _edge_weights(depth, smoothness, k, wh, wv):
    """Both weight arrays; without a depth term (k = 0) as branch-free loops that LLVM
    vectorises."""
    h, w = depth.shape
    zero = np.float32(0.0)
    if k == 0:
        for i in range(h):
            for j in range(w - 1):
                both = (depth[i, j] != 0) & (depth[i, j + 1] != 0)
                wh[i, j] = smoothness if both else zero
        for i in range(h - 1):
            for j in range(w):
                both = (depth[i, j] != 0) & (depth[i + 1, j] != 0)
                wv[i, j] = smoothness if both else zero
        return
    for i in range(h):
        for j in range(w - 1):
            wh[i, j] = _edge_weight(depth[i, j], depth[i, j + 1], smoothness, k)
    for i in range(h - 1):
        for j in range(w):
            wv[i, j] = _edge_weight(depth[i, j], depth[i + 1, j], smoothness, k)


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
    every other pixel must carry a class id below C.
    """
    arr = check_proba(proba_or_unaries)
    depth = check_depth_shape(depth, arr.shape[:2])
    labels = np.asarray(labels)
    if labels.shape != arr.shape[:2]:
        raise TopsegError(f"labels shape {labels.shape} does not match posteriors {arr.shape[:2]}")
    valid = depth > 0
    if np.any(labels[valid] >= arr.shape[2]):
        raise TopsegError(
            f"labels of pixels with depth must be class ids below the {arr.shape[2]} classes"
        )
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
