"""Boykov-Kolmogorov max-flow / min-cut in numba, for small graphs built many times a frame.

The same algorithm gco runs inside each alpha-expansion move (Boykov & Kolmogorov 2004,
"An experimental comparison of min-cut/max-flow algorithms"): two search trees grown
from the terminals, augmentation along the path where they meet, adoption of orphans.
Capacities are int64 so the cut is exact.

Graph layout (flat arrays, as scikit-learn's trees): edge e joins `u[e]` and `v[e]` with
capacity `cap_uv[e]` one way and `cap_vu[e]` back; arcs 2e (u->v) and 2e+1 (v->u) are
sisters (`a ^ 1`). Terminal capacities come as `tr = cap_source - cap_sink` per node
after the common part min(cap_source, cap_sink) is taken out as a constant.
"""

from __future__ import annotations

import numba
import numpy as np

_NONE = -1  # free node: in neither tree
_TERMINAL = -2  # parent is the source or the sink
_ORPHAN = -3  # lost its parent during augmentation
_INF = np.int64(1) << 62


@numba.njit(cache=True)
def build_csr(n, u, v):
    """Arcs out of every node: `adj[first[i]:first[i + 1]]`, and each arc's head."""
    m = u.shape[0]
    deg = np.zeros(n + 1, np.int64)
    for e in range(m):
        deg[u[e] + 1] += 1
        deg[v[e] + 1] += 1
    first = np.cumsum(deg)
    fill = first[:-1].copy()
    adj = np.empty(2 * m, np.int64)
    head = np.empty(2 * m, np.int64)
    for e in range(m):
        a = 2 * e
        head[a] = v[e]
        head[a + 1] = u[e]
        adj[fill[u[e]]] = a
        fill[u[e]] += 1
        adj[fill[v[e]]] = a + 1
        fill[v[e]] += 1
    return first, adj, head


@numba.njit(cache=True)
def _push_back(buf, tail, x):
    buf[tail] = x
    return (tail + 1) % buf.shape[0]


@numba.njit(cache=True)
def _adopt_orphans(
    first, adj, head, rcap, parent, is_sink, ts, dist, orphans, oh, ot, queue, qt, inq, time
):
    """Give every orphan a new parent in its own tree, or free it (BK's adoption stage)."""
    nbuf = orphans.shape[0]
    while oh != ot:
        i = orphans[oh]
        oh = (oh + 1) % nbuf
        sink = is_sink[i]
        d_min = _INF
        a0_min = _NONE
        for k in range(first[i], first[i + 1]):
            a0 = adj[k]
            # residual capacity towards i (source tree) or away from i (sink tree)
            if (rcap[a0] if sink else rcap[a0 ^ 1]) <= 0:
                continue
            j = head[a0]
            if is_sink[j] != sink or parent[j] == _NONE:
                continue
            d = 0
            while True:  # does j's path reach the terminal, and how far?
                if ts[j] == time:
                    d += dist[j]
                    break
                a = parent[j]
                d += 1
                if a == _TERMINAL:
                    ts[j] = time
                    dist[j] = 1
                    break
                if a == _ORPHAN:
                    d = _INF
                    break
                j = head[a]
            if d < _INF:
                if d < d_min:
                    a0_min = a0
                    d_min = d
                j = head[a0]  # mark the path so later searches stop early
                while ts[j] != time:
                    ts[j] = time
                    dist[j] = d
                    d -= 1
                    j = head[parent[j]]
        if a0_min != _NONE:
            parent[i] = a0_min
            ts[i] = time
            dist[i] = d_min + 1
            continue
        ts[i] = 0  # no way back: i becomes free; its tree neighbours may grow into it
        for k in range(first[i], first[i + 1]):
            a0 = adj[k]
            j = head[a0]
            if is_sink[j] != sink or parent[j] == _NONE:
                continue
            if (rcap[a0] if sink else rcap[a0 ^ 1]) > 0 and not inq[j]:
                inq[j] = True
                qt = _push_back(queue, qt, j)
            a = parent[j]
            if a >= 0 and head[a] == i:
                parent[j] = _ORPHAN
                ot = _push_back(orphans, ot, j)
        parent[i] = _NONE
    return oh, ot, qt


@numba.njit(cache=True)
def _augment(middle, head, rcap, tr, parent, orphans, ot):
    """Push the bottleneck along source -> middle arc -> sink; orphan saturated links."""
    b = rcap[middle]
    i = head[middle ^ 1]
    while parent[i] != _TERMINAL:
        a = parent[i]
        b = min(b, rcap[a ^ 1])
        i = head[a]
    b = min(b, tr[i])
    i = head[middle]
    while parent[i] != _TERMINAL:
        a = parent[i]
        b = min(b, rcap[a])
        i = head[a]
    b = min(b, -tr[i])

    rcap[middle ^ 1] += b
    rcap[middle] -= b
    i = head[middle ^ 1]
    while parent[i] != _TERMINAL:
        a = parent[i]
        rcap[a] += b
        rcap[a ^ 1] -= b
        if rcap[a ^ 1] == 0:
            parent[i] = _ORPHAN
            ot = _push_back(orphans, ot, i)
        i = head[a]
    tr[i] -= b
    if tr[i] == 0:
        parent[i] = _ORPHAN
        ot = _push_back(orphans, ot, i)
    i = head[middle]
    while parent[i] != _TERMINAL:
        a = parent[i]
        rcap[a ^ 1] += b
        rcap[a] -= b
        if rcap[a] == 0:
            parent[i] = _ORPHAN
            ot = _push_back(orphans, ot, i)
        i = head[a]
    tr[i] += b
    if tr[i] == 0:
        parent[i] = _ORPHAN
        ot = _push_back(orphans, ot, i)
    return b, ot


@numba.njit(cache=True)
def maxflow_csr(first, adj, head, rcap, tr):
    """Max-flow on a CSR graph; `rcap` (per arc) and `tr` (per node) are used up in place.

    Returns (flow through the non-terminal part, in_source bool per node). The flow does
    not include the constant taken out of the terminal links.
    """
    n = first.shape[0] - 1
    parent = np.full(n, _NONE, np.int64)
    is_sink = np.zeros(n, np.bool_)
    ts = np.zeros(n, np.int64)
    dist = np.zeros(n, np.int64)
    queue = np.empty(n + 1, np.int64)
    inq = np.zeros(n, np.bool_)
    orphans = np.empty(n + 1, np.int64)
    qh = qt = oh = ot = 0
    flow = 0
    # Greedy pushes along the shortest paths first (s -> u -> v -> t, then one hop
    # longer): cheap, and they carry most of an expansion move's flow.
    for a in range(head.shape[0]):
        u = head[a ^ 1]
        v = head[a]
        if tr[u] > 0 and tr[v] < 0 and rcap[a] > 0:
            b = min(tr[u], -tr[v], rcap[a])
            tr[u] -= b
            tr[v] += b
            rcap[a] -= b
            rcap[a ^ 1] += b
            flow += b
    for a in range(head.shape[0]):  # then s -> u -> v -> w -> t through a spent v
        u = head[a ^ 1]
        if tr[u] <= 0 or rcap[a] <= 0:
            continue
        v = head[a]
        if tr[v] != 0:
            continue
        for k in range(first[v], first[v + 1]):
            a2 = adj[k]
            w = head[a2]
            if tr[w] < 0 and rcap[a2] > 0:
                b = min(tr[u], -tr[w], rcap[a], rcap[a2])
                tr[u] -= b
                tr[w] += b
                rcap[a] -= b
                rcap[a ^ 1] += b
                rcap[a2] -= b
                rcap[a2 ^ 1] += b
                flow += b
                if tr[u] == 0 or rcap[a] == 0:
                    break
    for i in range(n):
        if tr[i] != 0:
            is_sink[i] = tr[i] < 0
            parent[i] = _TERMINAL
            dist[i] = 1
            inq[i] = True
            qt = _push_back(queue, qt, i)
    time = 0
    current = -1
    nbuf = n + 1
    while True:
        i = current
        if i >= 0:
            inq[i] = False
            if parent[i] == _NONE:
                i = -1
        if i < 0:
            while qh != qt:
                k = queue[qh]
                qh = (qh + 1) % nbuf
                inq[k] = False
                if parent[k] != _NONE:
                    i = k
                    break
            if i < 0:
                break
        middle = -1
        sink = is_sink[i]
        for k in range(first[i], first[i + 1]):
            a = adj[k]
            if (rcap[a ^ 1] if sink else rcap[a]) <= 0:
                continue
            j = head[a]
            if parent[j] == _NONE:
                is_sink[j] = sink
                parent[j] = a ^ 1
                ts[j] = ts[i]
                dist[j] = dist[i] + 1
                if not inq[j]:
                    inq[j] = True
                    qt = _push_back(queue, qt, j)
            elif is_sink[j] != sink:
                middle = a ^ 1 if sink else a
                break
            elif ts[j] <= ts[i] and dist[j] > dist[i]:
                parent[j] = a ^ 1
                ts[j] = ts[i]
                dist[j] = dist[i] + 1
        time += 1
        if middle >= 0:
            inq[i] = True  # stays current: scan it again after the adoption
            current = i
            b, ot = _augment(middle, head, rcap, tr, parent, orphans, ot)
            flow += b
            oh, ot, qt = _adopt_orphans(
                first,
                adj,
                head,
                rcap,
                parent,
                is_sink,
                ts,
                dist,
                orphans,
                oh,
                ot,
                queue,
                qt,
                inq,
                time,
            )
        else:
            current = -1
    in_source = np.empty(n, np.bool_)
    for i in range(n):
        in_source[i] = parent[i] != _NONE and not is_sink[i]
    return flow, in_source


@numba.njit(cache=True)
def mincut(n, u, v, cap_uv, cap_vu, cap_source, cap_sink):
    """Minimum s-t cut of a graph given as edge lists (int64 capacities).

    Returns (cut value, in_source bool per node). The cut value counts s->i for sink-side
    nodes, i->t for source-side nodes and u->v for u on the source side, v on the sink side.
    """
    first, adj, head = build_csr(n, u, v)
    rcap = np.empty(2 * u.shape[0], np.int64)
    for e in range(u.shape[0]):
        rcap[2 * e] = cap_uv[e]
        rcap[2 * e + 1] = cap_vu[e]
    tr = np.empty(n, np.int64)
    const = 0
    for i in range(n):
        tr[i] = cap_source[i] - cap_sink[i]
        const += min(cap_source[i], cap_sink[i])
    flow, in_source = maxflow_csr(first, adj, head, rcap, tr)
    return flow + const, in_source
