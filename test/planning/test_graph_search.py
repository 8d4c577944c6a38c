"""The compiled A* finds shortest paths: its costs equal scipy's Dijkstra on the same graph,
with masked vertices, blocked edges, and start/goal links (some blocked)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import sparse
from scipy.sparse import csgraph

from damon_ros.planning.graph_search import GOAL, START, GraphSearch


def _random_graph(rng, n: int, k: int):
    """A symmetric kNN-like graph in 7-D: CSR arrays and the vertex positions."""
    q = rng.uniform(-1, 1, (n, 7))
    rows, cols = [], []
    for i in range(n):
        d = np.linalg.norm(q - q[i], axis=1)
        for j in np.argsort(d)[1:k + 1]:
            rows += [i, j]
            cols += [j, i]
    w = np.linalg.norm(q[rows] - q[cols], axis=1)
    adj = sparse.coo_matrix((w, (rows, cols)), shape=(n, n)).tocsr()
    adj.data[:] = np.linalg.norm(q[adj.nonzero()[0]] - q[adj.indices], axis=1)
    return adj, q


def _reference(adj, active, blocked_pairs, start_links, goal_links, direct) -> float:
    """Dijkstra on the graph restricted the same way, start = n, goal = n + 1."""
    n = adj.shape[0]
    coo = adj.tocoo()
    keep = active[coo.row] & active[coo.col]
    keep &= np.array([(min(a, b), max(a, b)) not in blocked_pairs
                      for a, b in zip(coo.row, coo.col, strict=True)], bool)
    rows, cols, w = list(coo.row[keep]), list(coo.col[keep]), list(coo.data[keep])
    for v, c in start_links:
        if math.isfinite(c):
            rows.append(n)
            cols.append(v)
            w.append(c)
    for v, c in goal_links.items():
        if math.isfinite(c):
            rows.append(v)
            cols.append(n + 1)
            w.append(c)
    if math.isfinite(direct):
        rows.append(n)
        cols.append(n + 1)
        w.append(direct)
    full = sparse.coo_matrix((w, (rows, cols)), shape=(n + 2, n + 2)).tocsr()
    return float(csgraph.dijkstra(full, directed=True, indices=n)[n + 1])


def _cost(path, adj, start_links, goal_links, direct) -> float:
    if path == [START, GOAL]:
        return direct
    total = dict(start_links)[path[1]] + goal_links[path[-2]]
    return total + sum(adj[u, v] for u, v in zip(path[1:-2], path[2:-1], strict=True))


@pytest.mark.parametrize("seed", range(6))
def test_costs_equal_dijkstra_with_masks_and_blocked_edges(seed):
    rng = np.random.default_rng(seed)
    adj, q = _random_graph(rng, 300, 6)
    search = GraphSearch(adj.indptr, adj.indices, adj.data)
    active = rng.random(300) < 0.8
    blocked = set()
    for e in rng.choice(adj.nnz, 80, replace=False):
        u = int(np.searchsorted(adj.indptr, e, side="right") - 1)
        v = int(adj.indices[e])
        search.block(u, v)
        blocked.add((min(u, v), max(u, v)))
    q_start, q_goal = rng.uniform(-1, 1, (2, 7))
    ids = np.flatnonzero(active)
    near_s = ids[np.argsort(np.linalg.norm(q[ids] - q_start, axis=1))[:8]]
    near_g = ids[np.argsort(np.linalg.norm(q[ids] - q_goal, axis=1))[:8]]
    start_links = [(int(v), float(np.linalg.norm(q[v] - q_start))) for v in near_s]
    start_links[0] = (start_links[0][0], math.inf)  # a link known to be blocked
    goal_links = {int(v): float(np.linalg.norm(q[v] - q_goal)) for v in near_g}
    direct = math.inf if seed % 2 else 3.0 + float(np.linalg.norm(q_goal - q_start))
    heuristic = np.linalg.norm(q - q_goal, axis=1)  # admissible: straight-line distance

    path = search.shortest(active, heuristic, start_links, goal_links, direct)
    expected = _reference(adj, active, blocked, start_links, goal_links, direct)
    if not math.isfinite(expected):
        assert path is None
        return
    assert path is not None and path[0] == START and path[-1] == GOAL
    assert all(active[v] for v in path[1:-1])
    assert not any((min(u, v), max(u, v)) in blocked for u, v in zip(path[1:-2], path[2:-1],
                                                                      strict=True))
    assert _cost(path, adj, start_links, goal_links, direct) == pytest.approx(expected, rel=1e-9)


def test_no_path_when_the_goal_is_cut_off():
    rng = np.random.default_rng(1)
    adj, q = _random_graph(rng, 50, 4)
    search = GraphSearch(adj.indptr, adj.indices, adj.data)
    heuristic = np.zeros(50)
    active = np.ones(50, bool)
    assert search.shortest(active, heuristic, [(0, 0.1)], {}, math.inf) is None
    assert search.shortest(active, heuristic, [(0, 0.1)], {1: 0.1}, math.inf) is not None
    assert search.shortest(active, heuristic, [(0, 0.1)], {1: math.inf}, 2.0) == [START, GOAL]
