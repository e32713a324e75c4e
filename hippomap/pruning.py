"""Pruning: one node per block of space (paper Eq. 15, Fig. 7; spec §4).

The top layer of :class:`~hippomap.cognitive_map.CognitiveMap` below the per-step update. Online,
a node about to be created in a block of side ``prune_block_m`` that already holds an older node
(reachable along the graph, neither current nor among the last ``N_excl`` nodes) is not created:
the robot merges into the old node (:meth:`Pruning._merge_target`). In batch, :meth:`Pruning.prune`
keeps the oldest node of every block and moves the others' links and key frames to it. Pruning
sits above loop closing because a batch pass must remap, or reject, the pending loop hypotheses.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .geometry import between, compose, se2_between, se2_compose, se2_inverse
from .loop_closing import LoopClosing
from .loop_closure import Candidate
from .map_events import NodesPruned
from .map_graph import LOOP
from .robust_kernel import USED_WEIGHT

__all__ = ["Pruning", "block_representatives", "merged_frames", "merged_links"]

_compose3, _inv3, _between3 = se2_compose, se2_inverse, se2_between


def block_representatives(P: np.ndarray, b: float) -> tuple[np.ndarray, np.ndarray]:
    """(block index of every node, the oldest node of each node's block) for node poses ``P``
    (N, 3) and blocks of side ``b``."""
    n = len(P)
    blocks = np.floor(P[:, :2] / b).astype(np.int64)
    _, inv = np.unique(blocks, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    ids = np.arange(n)
    order = np.lexsort((ids, inv))
    first = np.ones(n, dtype=bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    rep_of_group = np.empty(inv.max() + 1, dtype=np.int64)
    rep_of_group[inv[order][first]] = order[first]
    return inv, rep_of_group[inv]


def merged_frames(F: np.ndarray, inv: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, int]:
    """(key frame of every kept node, number of frames dropped): a kept node's own frame, else the
    frame of the oldest node of its block that has one."""
    ids = np.arange(len(F))
    has = F >= 0
    fr_order = np.lexsort((ids, inv))
    fr_order = fr_order[has[fr_order]]
    grp = inv[fr_order]
    firstf = np.ones(len(fr_order), dtype=bool)
    firstf[1:] = grp[1:] != grp[:-1]
    frame_of_group = np.full(inv.max() + 1, -1, dtype=np.int64)
    frame_of_group[grp[firstf]] = F[fr_order[firstf]]
    newF = np.where(F[keep] >= 0, F[keep], frame_of_group[inv[keep]])
    return newF, int(has.sum() - (newF >= 0).sum())


def merged_links(
    P: np.ndarray, rep: np.ndarray, src: np.ndarray, dst: np.ndarray, tr: np.ndarray, loop: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(transform of every link between the representatives of its ends, which links to keep):
    re-expressed through the map's relative pose of member -> representative; self-links dropped,
    and duplicate pairs but for the first, unless they are ``loop`` links."""
    n, m = len(P), len(src)
    rs, rd = rep[src], rep[dst]
    new_tr = compose(compose(between(P[rs], P[src]), tr), between(P[dst], P[rd]))
    keep_link = rs != rd
    a, c = np.minimum(rs, rd), np.maximum(rs, rd)
    key = a * n + c
    _, first_idx = np.unique(key, return_index=True)
    dedup = np.zeros(m, dtype=bool)
    dedup[first_idx] = True
    keep_link &= dedup | loop
    return new_tr, keep_link


class Pruning(LoopClosing):
    """Online and batch pruning, over :class:`~hippomap.loop_closing.LoopClosing`."""

    def _merge_target(self, q: tuple[float, float, float]) -> int | None:
        """Online pruning (Eq. 15): the oldest node in the block of the pose ``q`` a new node would
        have, neither current nor among the last ``N_excl`` nodes and (``prune_graph_radius_m``)
        within that path along the graph from the current node; None: create the node."""
        cfg = self.cfg
        cur = self._cur
        n = self._n
        b = cfg.prune_block_m
        same = np.all(np.floor(self._P[:n, :2] / b) == np.floor(np.array(q[:2]) / b), axis=1)
        same[cur] = False
        same[max(0, n - cfg.exclude_recent) :] = False
        if same.any() and cfg.prune_graph_radius_m is not None:
            same &= self._graph_distance(cur, cfg.prune_graph_radius_m) <= cfg.prune_graph_radius_m
        if same.any():
            return int(np.argmax(same))  # the oldest node of the block
        return None

    def _graph_distance(self, source: int, limit: float) -> np.ndarray:
        """Shortest path length (m, along links, either direction) from ``source`` to every node,
        ``inf`` beyond ``limit``. Builds a sparse graph: O(M).

        Loop links the robust kernel has faded (weight < ``USED_WEIGHT``) are not paths: a false
        closure would otherwise let online pruning merge the robot into a node it only reaches
        through that closure, a second false closure made as stiff as odometry (measured on a
        simulated loop: a faded link 162 → 3 let node 164 merge into node 4 across a lap of drift,
        1.1 rad apart, and that merge then held the first lap's seam open)."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import dijkstra

        n, m = self._n, self._m
        path = (self._kind[:m] != LOOP) | (self._w[:m] >= USED_WEIGHT)
        if not path.any():
            d = np.full(n, np.inf)
            d[source] = 0.0
            return d
        a = np.minimum(self._src[:m], self._dst[:m])[path]
        b = np.maximum(self._src[:m], self._dst[:m])[path]
        w = np.hypot(self._tr[:m, 0], self._tr[:m, 1])[path] + 1e-9  # explicit zeros would vanish
        key, inv = np.unique(a * n + b, return_inverse=True)  # parallel links: keep the shortest
        wmin = np.full(len(key), np.inf)
        np.minimum.at(wmin, inv.reshape(-1), w)
        g = csr_matrix((wmin, (key // n, key % n)), shape=(n, n))
        return dijkstra(g, directed=False, indices=source, limit=limit)

    # ------------------------------------------------------------------ batch pruning
    def prune(self) -> np.ndarray:
        """Batch pruning pass (Eq. 15; spec §4, optional): in each block of side b keep the
        oldest node; the others' links are moved to it (their transforms re-expressed through
        the map's current relative pose of the two nodes, self-links and duplicate pairs
        dropped), their key frame moves to it if it has none. Node ids are compacted.

        Returns ``old_to_new`` (N_old,) mapping every old node id to its new id. The robot's
        current node and offset, and pending hypotheses, are remapped; each loop decision's link is
        renumbered with the links (-1 when its link was merged into another or became a self-link).
        """
        n, m = self._n, self._m
        P = self._P[:n].copy()
        inv, rep = block_representatives(P, self.cfg.prune_block_m)
        keep = rep == np.arange(n)
        old_to_new = (np.cumsum(keep) - 1)[rep]
        newF, frames_dropped = merged_frames(self._F[:n].copy(), inv, keep)
        new_tr, keep_link = merged_links(P, rep, self._src[:m], self._dst[:m], self._tr[:m], self._kind[:m] == LOOP)
        # the robot, in the frame of its node's representative
        delta = _between3(P[int(rep[self._cur])], _compose3(P[self._cur], self._delta))
        # compact nodes
        kn = int(keep.sum())
        for name in ("_P", "_C", "_Tn", "_S"):
            arr = getattr(self, name)
            arr[:kn] = arr[:n][keep]
        self._F[:kn] = newF
        self._F[kn:] = -1
        self._n = kn
        ml = self._compact_links(keep_link, new_tr, old_to_new)
        self._version += 1
        self._dirty = True
        self._touched = [-1]
        self._cur = int(old_to_new[self._cur])
        self._delta = delta
        code = self._robot_code()
        self._anchor = None if code is None else _compose3(code, _inv3(delta))
        t = self._t if self._t is not None else 0.0
        self._arrival = -1
        self._remap_loops(old_to_new, np.where(keep_link, np.cumsum(keep_link) - 1, -1), t)
        self._events.append(NodesPruned(n - kn, kn, ml, frames_dropped, t))
        self._events.extend(self._optimise(t, force=True))
        return old_to_new

    def _compact_links(self, keep_link: np.ndarray, new_tr: np.ndarray, old_to_new: np.ndarray) -> int:
        """Keep the links ``keep_link`` with transforms ``new_tr`` between the new node ids, recolour
        them; returns the new link count."""
        m = self._m
        src, dst = self._src[:m], self._dst[:m]
        kl = np.flatnonzero(keep_link)
        ml = len(kl)
        s_new, d_new = old_to_new[src[kl]], old_to_new[dst[kl]]
        self._tr[:ml] = new_tr[kl]
        self._dt[:ml] = self._dt[:m][kl]
        self._w[:ml] = self._w[:m][kl]
        self._linfo[:ml] = self._linfo[:m][kl]
        self._lkw[:ml] = self._lkw[:m][kl]
        self._lcoup[:ml] = self._lcoup[:m][kl]
        self._lkpos[:ml] = self._lkpos[:m][kl]
        self._kind[:ml] = self._kind[:m][kl]
        self._src[:ml], self._dst[:ml] = s_new, d_new
        self._m = ml
        self._rebuild_link_index()
        return ml

    def _remap_loops(self, old_to_new: np.ndarray, link_to_new: np.ndarray, t: float) -> None:
        """Pending, accepted and faded candidates renamed to the new node ids (their arrival links are
        gone), and every decision's link to its new index (``link_to_new``, -1: dropped); a pending
        candidate whose node was merged into the node it was proposed from is rejected."""

        def remap(c: Candidate) -> Candidate:
            return replace(c, node=int(old_to_new[c.node]), from_node=int(old_to_new[c.from_node]), arrival=-1)

        book = self._loops
        for cand in book.pending:
            if old_to_new[cand.node] == old_to_new[cand.from_node]:
                self._reject(cand.id, "prune() merged its node into the node it was proposed from", t)
        book.pending = [remap(c) for c in book.pending if old_to_new[c.node] != old_to_new[c.from_node]]
        book.accepted = [remap(c) for c in book.accepted]
        book.faded = [remap(c) for c in book.faded]  # judged by their decisions' renumbered links
        book.decisions = [d if d.link < 0 else replace(d, link=int(link_to_new[d.link])) for d in book.decisions]
