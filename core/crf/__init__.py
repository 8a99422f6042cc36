"""Potts CRF over forest posteriors (paper section IV): one energy, two ways to minimise it.

E(x) = sum_p U_p(x_p) + sum_{p~q} w_pq [x_p != x_q]

- U_p(l) = -log(max(P(l | p), eps)): the forest's posterior as a unary, in nats.
- p~q runs over 4-connected pairs of pixels that both have depth; pixels without depth
  (depth == 0) take no part and come out as NO_DEPTH.
- w_pq = smoothness * exp(-(d_p - d_q)^2 / (2 depth_sigma_mm^2)): a Potts weight, cut down
  across depth discontinuities when `depth_sigma_mm` > 0 (0 = the paper's plain Potts).

Modes: `none` (argmax), `exact` (alpha-expansion with gco over the full grid, the paper's
method) and `realtime` (`topseg.core.crf.realtime`: the same energy, minimised by a numba
alpha-expansion on the uncertain band only). Both solvers work on integers: unaries and
weights are multiplied by ENERGY_SCALE and rounded (0.001-nat resolution); reported
energies are always recomputed in float from the labeling by `potts_energy`, the one
definition every mode and test uses. See docs/explanation/crf.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from topseg.core.crf.argmax import Summary, argmax_confidence, segment_argmax
from topseg.core.crf.energy import (
    ENERGY_SCALE,
    MAX_SMOOTHNESS,
    MODES,
    CRFConfig,
    Mode,
    check_depth_shape,
    check_proba,
    edge_weights,
    grid_edges,
    grid_energy,
    potts_energy,
    unaries_from_posteriors,
)
from topseg.core.crf.exact import gco_expansion, segment_exact
from topseg.core.crf.realtime import segment_realtime

__all__ = [
    "ENERGY_SCALE",
    "MAX_SMOOTHNESS",
    "MODES",
    "CRFConfig",
    "Mode",
    "Summary",
    "argmax_confidence",
    "edge_weights",
    "gco_expansion",
    "grid_edges",
    "grid_energy",
    "potts_energy",
    "segment_argmax",
    "segment_crf",
    "segment_exact",
    "segment_realtime",
    "unaries_from_posteriors",
]


def segment_crf(
    proba: np.ndarray,
    depth_u16: np.ndarray,
    config: CRFConfig,
    summary: Summary | None = None,
    fill: Callable[[np.ndarray], object] | None = None,
) -> np.ndarray:
    """(H, W) uint8 labels minimising the Potts energy under `config.mode`.

    Pixels with depth == 0 come out NO_DEPTH and take no part in the graph. `summary`, when
    given, is `proba`'s argmax and top two posteriors (`argmax.Summary`, as the forest fills
    it): the realtime and argmax modes then skip that pass over `proba`. `fill(mask)`, when
    given, stores posteriors into `proba` at the (H, W) bool mask before they are read
    there (`segment_realtime`; the argmax mode reads none, `exact` asks for all): for a
    lazy `forest.predict_proba`.
    """
    if fill is not None and (config.mode == "exact" or summary is None):
        fill(np.ones(np.shape(depth_u16), np.bool_))  # every posterior is read
        fill = None
    proba = check_proba(proba)
    depth = check_depth_shape(depth_u16, proba.shape[:2])
    valid = depth > 0
    if config.mode == "none":
        return segment_argmax(proba, valid) if summary is None else summary.amax.copy()
    if config.mode == "exact":
        wh, wv = edge_weights(depth, config)
        unary = unaries_from_posteriors(proba, config.eps)
        labels = segment_exact(unary, wh, wv, valid)
        # gco minimises the int32-rounded energy; keep the promise in float as well
        argmax = segment_argmax(proba, valid)
        if grid_energy(labels, unary, wh, wv, valid) > grid_energy(argmax, unary, wh, wv, valid):
            return argmax
        return labels
    return segment_realtime(proba, depth, config, summary, fill)
