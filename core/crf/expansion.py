"""Alpha-expansion for Potts energies in numba, with each move's graph pruned exactly.

Boykov, Veksler & Zabih (2001): repeat, for every label alpha, the best "expansion move"
(each site keeps its label or takes alpha), found as a minimum cut, until no move lowers
the energy. The result is within a factor 2 of the optimum for Potts, and its energy
never rises above the starting labeling's.

Pruning: in the move for alpha, a site p that would pay U_p(alpha) - U_p(x_p) >= W_p
(the sum of its edge weights) to switch can keep its label in some optimal move whatever
its neighbours do, so it is left out of the graph. With forest posteriors most sites have
a near-zero posterior for most labels, so each move's graph is a small fraction of the
sites: this is what makes the real-time CRF fast.

Problems come as integer energies (int64, see `topseg.core.crf.ENERGY_SCALE`): unary
(N, K), and a neighbour table `nbr` (N, D) with -1 for no neighbour and symmetric weights
`nw` (N, D), each undirected edge listed from both ends.
"""

from __future__ import annotations

import numba
import numpy as np

from topseg.core.crf.maxflow import mincut


@numba.njit(cache=True)
def energy(x, unary, nbr, nw):
    """Potts energy of labels `x` (int64): unaries plus each cut edge once."""
    n, d = nbr.shape
    total = 0
    for p in range(n):
        total += unary[p, x[p]]
        for s in range(d):
            q = nbr[p, s]
            if q > p and x[q] != x[p]:
                total += nw[p, s]
    return total


@numba.njit(cache=True)
def expansion_move(alpha, x, ux, unary_t, nbr, nw, wsum, loc, nodes, slack):
    """Apply the best alpha-expansion move to `x` in place; returns how much it lowered
    the energy (0: no move helps, `x` unchanged).

    `ux[p]` is p's unary under `x` (kept up to date), `unary_t` the unaries as (K, N).
    `loc`, `nodes` and `slack` (N,) are scratch buffers. y_p = 0 keeps x_p (source side
    of the cut), y_p = 1 takes alpha (sink side).
    """
    n, d = nbr.shape
    ua = unary_t[alpha]
    # 1. prune exactly. slack[p] bounds what switching p to alpha can save: the edges
    #    that may give back their weight (to alpha, or to sites still in the move) minus
    #    the unary increase, minus edges to left-out sites with p's own label (switching
    #    would cut them). slack <= 0: p keeps its label in some optimal move, whatever
    #    the others do, so it is left out; that tightens its neighbours' bounds in turn.
    #    loc: -2 already alpha, -1 left out, 0 in the move, -3 left out, to propagate.
    m = 0
    for p in range(n):  # branch-free: every site written, the kept ones counted
        is_alpha = x[p] == alpha
        sl = wsum[p] - (ua[p] - ux[p])
        keep = (not is_alpha) & (sl > 0)
        loc[p] = 0 if keep else (-2 if is_alpha else -1)
        slack[p] = sl
        nodes[m] = p
        m += keep
    if m == 0:
        return 0
    stack = np.empty(m, np.int64)
    top = 0
    for i in range(m):  # edges to sites left out in the first pass (branch-free)
        p = nodes[i]
        xp = x[p]
        sl = slack[p]
        for s in range(d):
            q = nbr[p, s]
            r = max(q, 0)
            out = (q >= 0) & (loc[r] == -1)
            sl -= out * nw[p, s] * (1 + (x[r] == xp))
        slack[p] = sl
        drop = sl <= 0
        loc[p] = -3 if drop else 0
        stack[top] = p
        top += drop
    while top > 0:
        top -= 1
        p = stack[top]
        loc[p] = -1
        for s in range(d):
            r = nbr[p, s]
            if r < 0 or loc[r] != 0:
                continue
            slack[r] -= nw[p, s] * (2 if x[r] == x[p] else 1)
            if slack[r] <= 0:
                loc[r] = -3
                stack[top] = r
                top += 1
    k = 0
    for i in range(m):
        p = nodes[i]
        kept = loc[p] == 0
        loc[p] = k if kept else loc[p]
        nodes[k] = p
        k += kept
    m = k
    if m == 0:
        return 0
    # 2. the move as a min cut
    ne = 0
    for i in range(m):
        p = nodes[i]
        for s in range(d):
            q = nbr[p, s]
            if q > p and loc[q] >= 0 and nw[p, s] > 0:
                ne += 1
    c0 = np.zeros(m, np.int64)  # cost of keeping, paid on the source side
    c1 = np.zeros(m, np.int64)  # cost of taking alpha, paid on the sink side
    eu = np.empty(ne, np.int64)
    ev = np.empty(ne, np.int64)
    cuv = np.empty(ne, np.int64)
    cvu = np.empty(ne, np.int64)
    e = 0
    for i in range(m):
        p = nodes[i]
        xp = x[p]
        c0[i] += ux[p]
        c1[i] += ua[p]
        for s in range(d):
            q = nbr[p, s]
            w = nw[p, s]
            if q < 0 or w == 0:
                continue
            xq = x[q]
            if xq == alpha:  # q is alpha already: keeping x_p != alpha cuts the edge
                c0[i] += w
            elif loc[q] < 0:  # q keeps x_q (left out, or not in the move)
                if xp != xq:
                    c0[i] += w
                c1[i] += w
            elif q > p:  # both in the move: one edge, listed once
                j = loc[q]
                eu[e] = i
                ev[e] = j
                cuv[e] = w
                if xp == xq:  # w [y_p != y_q]
                    cvu[e] = w
                else:  # w [y_q = 0] + w [y_p = 0, y_q = 1]
                    cvu[e] = 0
                    c0[j] += w
                e += 1
    keep_all = 0
    for i in range(m):
        keep_all += c0[i]
    cut, in_source = mincut(m, eu, ev, cuv, cvu, c1, c0)
    if cut >= keep_all:
        return 0
    for i in range(m):
        if not in_source[i]:
            p = nodes[i]
            x[p] = alpha
            ux[p] = ua[p]
    return keep_all - cut


@numba.njit(cache=True)
def expansion_run(unary, nbr, nw, x0, max_cycles=100):
    """(labels (int64), energy decrease) from `x0` by expansion moves, label after label,
    until a whole round of labels brings no change (or `max_cycles` rounds)."""
    n, k = unary.shape
    x = x0.astype(np.int64).copy()
    wsum = np.zeros(n, np.int64)
    for p in range(n):
        for s in range(nbr.shape[1]):
            if nbr[p, s] >= 0:
                wsum[p] += nw[p, s]
    unary_t = np.ascontiguousarray(unary.T)
    ux = np.empty(n, np.int64)
    for p in range(n):
        ux[p] = unary[p, x[p]]
    loc = np.empty(n, np.int64)
    nodes = np.empty(n, np.int64)
    slack = np.empty(n, np.int64)
    gain = 0
    last_change = -1  # move number of the last move that changed x
    move = 0
    for _ in range(max_cycles):
        for alpha in range(k):
            if move >= k and move - last_change >= k:  # all failed since the last change
                return x, gain
            g = expansion_move(alpha, x, ux, unary_t, nbr, nw, wsum, loc, nodes, slack)
            if g > 0:
                gain += g
                last_change = move
            move += 1
    return x, gain


@numba.njit(cache=True)
def alpha_expansion(unary, nbr, nw, x0, max_cycles=100):
    """Labels (int64) from `x0` by expansion moves (`expansion_run` without the gain)."""
    return expansion_run(unary, nbr, nw, x0, max_cycles)[0]


def grid_neighbours(h: int, w: int, wh: np.ndarray, wv: np.ndarray, index: np.ndarray):
    """Neighbour table (N, 4) and int weights of a 4-connected grid's indexed pixels.

    `index` (H, W) numbers the sites (-1 = not a site); `wh`/`wv` are int64 edge weights.
    """
    n = int(index.max()) + 1 if index.size else 0
    nbr = np.full((n, 4), -1, np.int64)
    nw = np.zeros((n, 4), np.int64)
    pad = np.full((h + 2, w + 2), -1, np.int64)
    pad[1:-1, 1:-1] = index
    wpad_h = np.zeros((h, w + 1), np.int64)
    wpad_h[:, 1:-1] = wh
    wpad_v = np.zeros((h + 1, w), np.int64)
    wpad_v[1:-1, :] = wv
    sites = index >= 0
    ids = index[sites]
    neighbours = (pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1])
    weights = (wpad_h[:, :-1], wpad_h[:, 1:], wpad_v[:-1, :], wpad_v[1:, :])
    for s, (q, wq) in enumerate(zip(neighbours, weights, strict=True)):
        nbr[ids, s] = q[sites]
        nw[ids, s] = wq[sites]
    nw[nbr < 0] = 0
    return nbr, nw
