"""The union-find root that the blob kernels share (`person_check_kernels.label8`,
`surfaces.vote_surfaces`): numba, over a flat int32 parent array."""

from __future__ import annotations

import numba


@numba.njit(cache=True)
def find_root(parent, x):
    """The root of x in the union-find forest `parent`, halving the path on the way."""
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x
