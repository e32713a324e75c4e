"""Shortest paths over the map's links, undirected: link counts (hops) and path lengths (spec §4).

The map correction's local windows count links from the closures (:func:`hop_distances`); the loop gate's drift
path (:meth:`~hippomap.map_graph.MapGraph.graph_path`) is the shortest path over the map's links from a node,
remembered per graph content (:class:`GraphPaths`). Both run scipy's Dijkstra on a graph built here with every
link stored in both directions (:func:`_both_ways`).
"""

from __future__ import annotations

from typing import cast

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

__all__ = ["GraphPaths", "hop_distances"]


def _both_ways(n: int, src: np.ndarray, dst: np.ndarray, weight: np.ndarray) -> csr_matrix:
    """The (n, n) CSR graph with every link ``src → dst`` stored in both directions with its
    ``weight`` (parallel links kept apart), built directly: for a directed Dijkstra that reaches
    what an undirected one on the links reaches."""
    rows = np.concatenate([src, dst])
    by_row = np.argsort(rows, kind="stable")  # two nearly sorted runs: cheap
    indptr = np.zeros(n + 1, dtype=np.int32)
    np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
    cols = np.concatenate([dst, src])[by_row].astype(np.int32)
    return csr_matrix((np.concatenate([weight, weight])[by_row], cols, indptr), shape=(n, n), copy=False)


def hop_distances(n: int, src: np.ndarray, dst: np.ndarray, seeds: np.ndarray, hops: int) -> np.ndarray:
    """(n,) the number of links (either direction) from the nearest of ``seeds`` to each node, ``inf``
    beyond ``hops``: one breadth-first search from all seeds at once (an unweighted multi-source
    Dijkstra counts links: whole numbers, compared exactly) instead of ``hops`` passes over every link."""
    if hops <= 0 or not len(src):
        out = np.full(n, np.inf)
        out[seeds] = 0.0
        return out
    g = _both_ways(n, src, dst, np.ones(len(src)))
    d = dijkstra(g, directed=True, indices=np.unique(seeds), unweighted=True, min_only=True, limit=hops + 0.5)
    return cast(np.ndarray, d)


def _undirected_paths_reference(
    n: int, src: np.ndarray, dst: np.ndarray, length: np.ndarray, source: int
) -> np.ndarray:
    """Shortest paths from ``source`` over the undirected links ``src``–``dst`` of ``length``, as
    :meth:`~hippomap.map_graph.MapGraph.graph_path` has always computed them: links of the same direction between the
    same two nodes count as one link as long as their sum (``csr_matrix`` sums duplicates)."""
    g = csr_matrix((length, (src, dst)), shape=(n, n))
    return cast(np.ndarray, dijkstra(g, directed=False, indices=source))


def _undirected_paths(n: int, src: np.ndarray, dst: np.ndarray, length: np.ndarray, source: int) -> np.ndarray:
    """:func:`_undirected_paths_reference` on a graph built without scipy's conversions: the same
    numbers, about 3 × cheaper on a 2700-node map.

    Why it is exact: scipy's undirected Dijkstra relaxes, from each node, its row of the graph
    and its row of the transpose; a directed Dijkstra on the graph with every link stored in both
    directions relaxes the same (neighbour, length) pairs. Dijkstra's distances depend only on
    that multiset of weighted edges, not on the order they are stored or visited in (each
    distance is the minimum of ``d(u) + w`` over the node's edges, with all weights > 0), so the
    two agree bit for bit. Duplicate (source, target) pairs are summed as ``csr_matrix`` sums
    them; two duplicates sum the same either way (``a + b == b + a``); three or more would depend
    on the order of scipy's unstable index sort, so such graphs take the reference path."""
    key = np.sort(src * n + dst, kind="stable")  # nearly sorted already (links are appended as the robot goes)
    if len(key) > 1 and np.any(key[1:] == key[:-1]):  # parallel links of one direction
        start = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1])))
        if np.diff(np.append(start, len(key))).max() > 2:
            return _undirected_paths_reference(n, src, dst, length, source)
        order = np.argsort(src * n + dst, kind="stable")
        length = np.add.reduceat(length[order], start)  # runs of 1 or 2 links: exact in any order
        src, dst = key[start] // n, key[start] % n
    return cast(np.ndarray, dijkstra(_both_ways(n, src, dst, length), directed=True, indices=source))


class GraphPaths:
    """The memo of :meth:`~hippomap.map_graph.MapGraph.graph_path`: the last graph's kept links (node count, ends,
    lengths) and the distances from each source asked on it.

    Keyed on the links' content, compared in full on every call (a few microseconds): any change
    of the graph, of a link's length or of which loop links are used, however it was made (a
    closure, a reweighting, pruning, a test writing a weight), gives another key and new
    distances. No version counter has to be kept in step with every writer of the arrays."""

    def __init__(self) -> None:
        self._key: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._dist: dict[int, np.ndarray] = {}

    def distances(self, n: int, src: np.ndarray, dst: np.ndarray, length: np.ndarray, source: int) -> np.ndarray:
        """Shortest paths (m) from ``source`` to every node (read-only; ``inf``: not reached)."""
        k = self._key
        if not (
            k is not None
            and k[0] == n
            and np.array_equal(k[1], src)
            and np.array_equal(k[2], dst)
            and np.array_equal(k[3], length)
        ):
            self._key = (n, src.copy(), dst.copy(), length.copy())
            self._dist = {}
        d = self._dist.get(source)
        if d is None:
            d = _undirected_paths(n, src, dst, length, source)
            d.flags.writeable = False
            self._dist[source] = d
        return d
