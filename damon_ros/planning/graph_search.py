"""Compiled A* over the latent graph's CSR arrays, for the lazy (edge-checked) search.

Why compiled: the lazy search repeats A* once per blocked edge it meets (54-73 times for a
box that blocks the direct route), and a Python A* over 20,766 vertices took 5-10 ms each,
so a re-route ran out of its 0.25 s budget while sampling planners under the same checker
found a route in 60 ms. The same search compiled with numba (cached on disk) takes well under
a millisecond per iteration (`damon-ros bench-search`).

The graph is taken as it is stored (``indptr``, ``indices``, ``weights``) and restricted by
masks rather than copied: ``active`` vertices (the searched obstacle subgraphs), and
``blocked`` CSR entries (edges found invalid). The start and the goal are two extra nodes,
tied to graph vertices by ``start_ids``/``start_w`` and ``goal_cost`` (inf: no link), and to
each other by ``direct`` (inf: blocked).
"""

from __future__ import annotations

import numpy as np
from numba import njit

START = -1
GOAL = -2


@njit(cache=True)
def _push(heap_f, heap_v, size, f, v):
    """Binary min-heap on parallel arrays (key, node); returns the new size."""
    i = size
    heap_f[i], heap_v[i] = f, v
    while i > 0:
        parent = (i - 1) >> 1
        if heap_f[parent] <= heap_f[i]:
            break
        heap_f[i], heap_f[parent] = heap_f[parent], heap_f[i]
        heap_v[i], heap_v[parent] = heap_v[parent], heap_v[i]
        i = parent
    return size + 1


@njit(cache=True)
def _pop(heap_f, heap_v, size):
    """(node, new size) of the least key."""
    v = heap_v[0]
    size -= 1
    heap_f[0], heap_v[0] = heap_f[size], heap_v[size]
    i = 0
    while True:
        left = 2 * i + 1
        if left >= size:
            break
        child = left
        if left + 1 < size and heap_f[left + 1] < heap_f[left]:
            child = left + 1
        if heap_f[i] <= heap_f[child]:
            break
        heap_f[i], heap_f[child] = heap_f[child], heap_f[i]
        heap_v[i], heap_v[child] = heap_v[child], heap_v[i]
        i = child
    return v, size


@njit(cache=True)
def _astar(indptr, indices, weights, active, blocked, heuristic, start_ids, start_w,
           goal_cost, direct):
    """Shortest start → goal path as node ids (START, vertices..., GOAL); empty if none.
    Internally the start is node n and the goal n + 1."""
    n = len(indptr) - 1
    s, g = n, n + 1
    cost = np.full(n + 2, np.inf)
    parent = np.full(n + 2, -1, np.int64)
    closed = np.zeros(n + 2, np.bool_)
    capacity = len(indices) + len(start_ids) + n + 4
    heap_f = np.empty(capacity)
    heap_v = np.empty(capacity, np.int64)
    cost[s] = 0.0
    size = _push(heap_f, heap_v, 0, direct if np.isfinite(direct) else 0.0, s)
    while size > 0:
        u, size = _pop(heap_f, heap_v, size)
        if closed[u]:
            continue
        closed[u] = True
        if u == g:
            break
        if u == s:
            if direct < cost[g]:
                cost[g], parent[g] = direct, s
                size = _push(heap_f, heap_v, size, direct, g)
            for j in range(len(start_ids)):
                v = start_ids[j]
                c = start_w[j]
                if np.isfinite(c) and c < cost[v] and not closed[v]:
                    cost[v], parent[v] = c, s
                    size = _push(heap_f, heap_v, size, c + heuristic[v], v)
            continue
        c = cost[u] + goal_cost[u]
        if c < cost[g]:
            cost[g], parent[g] = c, u
            size = _push(heap_f, heap_v, size, c, g)
        for e in range(indptr[u], indptr[u + 1]):
            v = indices[e]
            if blocked[e] or not active[v] or closed[v]:
                continue
            c = cost[u] + weights[e]
            if c < cost[v]:
                cost[v], parent[v] = c, u
                size = _push(heap_f, heap_v, size, c + heuristic[v], v)
    if not closed[g]:
        return np.zeros(0, np.int64)
    length = 1
    v = g
    while v != s:
        v = parent[v]
        length += 1
    path = np.empty(length, np.int64)
    v = g
    for i in range(length - 1, -1, -1):
        path[i] = START if v == s else GOAL if v == g else v
        if v != s:
            v = parent[v]
    return path


class GraphSearch:
    """The lazy search's state over one graph: which edges are blocked for this query.

    ``block(u, v)`` removes an edge for every later ``shortest`` of the same query; the
    start's and goal's links are given per call (they depend on the searched subgraphs)."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, weights: np.ndarray) -> None:
        self.indptr = np.ascontiguousarray(indptr, np.int64)
        self.indices = np.ascontiguousarray(indices, np.int64)
        self.weights = np.ascontiguousarray(weights, np.float64)
        self.blocked = np.zeros(len(self.indices), np.bool_)

    def block(self, u: int, v: int) -> None:
        """Both directions of the graph edge u–v (the adjacency is symmetric)."""
        for a, b in ((u, v), (v, u)):
            lo, hi = self.indptr[a], self.indptr[a + 1]
            self.blocked[lo + np.flatnonzero(self.indices[lo:hi] == b)] = True

    def shortest(self, active: np.ndarray, heuristic: np.ndarray,
                 start_links: list[tuple[int, float]], goal_links: dict[int, float],
                 direct: float) -> list[int] | None:
        """Node ids START, vertices…, GOAL of the shortest path, or None. A link weight of
        inf (or a ``direct`` of inf) is a link known to be blocked."""
        n = len(self.indptr) - 1
        goal_cost = np.full(n, np.inf)
        for v, w in goal_links.items():
            goal_cost[v] = w
        start_ids = np.array([v for v, _ in start_links], np.int64)
        start_w = np.array([w for _, w in start_links], np.float64)
        path = _astar(self.indptr, self.indices, self.weights, active, self.blocked,
                      heuristic, start_ids, start_w, goal_cost, float(direct))
        return path.tolist() if len(path) else None
