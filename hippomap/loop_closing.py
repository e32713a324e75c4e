"""Loop closing on the map: hypotheses gated, verified, linked and weighted (paper §2.4; spec §4).

The layer of :class:`~hippomap.cognitive_map.CognitiveMap` that decides which loop links the map
gets and how much it trusts them (the data and maths it uses are in :mod:`hippomap.loop_closure`).
Loop closures enter through one door, :meth:`LoopClosing.propose_loop`, and are checked by (a) a
place-code gate whose radius grows with the path travelled since the matched node and (b) cycle
consistency between hypotheses; an accepted group of visual hypotheses has its relative pose
fitted before it becomes loop links. With ``loop_accept = 'robust'`` a gated hypothesis becomes a
link at once, weighted by the robust kernel (revised by :mod:`hippomap.map_correction` as the map
converges); visual hypotheses that fall outside the gate wait for a consistent group.
Every decision is kept in :attr:`LoopClosing.loop_decisions`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .errors import InputError
from .geometry import se2_between, se2_compose, se2_inverse
from .loop_closure import Candidate, LoopDecision, LoopHypothesis, consistent
from .loop_gate import OBLIQUE, OUTER_PART
from .loop_pose import fit_group
from .loop_record import GROUP_VERIFIED, LoopRecord
from .map_events import LoopAccepted, LoopPending
from .map_graph import LOOP, PRUNE

__all__ = ["LONG_GROUP", "LoopClosing"]

#: how the reason of a closure accepted with a long group turned beyond a group's heading bound ends (item 130)
LONG_GROUP = "a long group turned beyond a group's heading bound"

_compose3, _inv3, _between3 = se2_compose, se2_inverse, se2_between


class LoopClosing(LoopRecord):
    """Loop hypotheses and their decisions, over :class:`~hippomap.loop_record.LoopRecord`."""

    def propose_loop(self, h: LoopHypothesis) -> LoopDecision:
        """Offer a loop closure; returns the decision. Its events are queued: the caller takes them
        with :meth:`take_events` (else they come out of the next :meth:`update`).

        Checks, in order (see :mod:`hippomap.loop_closure`):

        * ``node`` must be an existing node, not the current one nor among the last ``N_excl``.
        * (a) gate: where the hypothesis puts the node (the robot's map pose ⊕ the node's pose in
          the robot's frame) must lie within :func:`~hippomap.loop_closure.gate_limit` of the
          node's map pose (``loop_gate = 'map'``), or of its place code from the robot's place
          code (``'place_code'``, Eq. 13 as in [S]).
        * (b) with ``loop_min_support`` ≥ 2, cycle consistency with the other hypotheses made
          within ``loop_support_window_m`` metres of path: with ``loop_min_support`` − 1
          consistent pending ones, or one consistent accepted one, it is accepted; if it
          contradicts every loop accepted in the window it is rejected; else it waits.

        Accepting a group of visual hypotheses first fits their relative pose together
        (:func:`~hippomap.loop_pose.align_group`), then adds a ``loop`` link per hypothesis
        from the node that was current at the proposal to ``node``; the newest relocalises the
        robot (current = its node, the robot's offset kept); then the map is corrected.
        Rejected hypotheses never touch node poses.
        """
        if not isinstance(h, LoopHypothesis):
            raise InputError(f"propose_loop needs a LoopHypothesis, got {type(h).__name__}")
        n = self._n
        if not 0 <= h.node < n:
            raise InputError(f"LoopHypothesis.node {h.node} is not a node id of this map [0, {n})")
        cfg = self.cfg
        book = self._loops
        cand = self._candidate(h)
        t = self._t if self._t is not None else h.time
        base, reason, outside, turned = self._screen(h, cand)
        book.decisions.append(base)
        waits = cfg.outside_searches == "all" or h.meta.get("search") == "global"  # else the gate rejects it
        if outside and waits and not h.measured and cfg.outside_min_support > 0:
            return self._propose_outside(replace(cand, turned=turned), t, reason)
        if reason:
            return self._reject(cand.id, reason, t)
        if cfg.loop_accept == "robust":
            return self._accept_robust(cand, t)
        if cfg.loop_min_support <= 1:
            self._accept([cand], cand, t)
            return book.decisions[cand.id]
        return self._verify(cand, t)

    def _candidate(self, h: LoopHypothesis) -> Candidate:
        """The candidate of hypothesis ``h`` proposed now (its decision id: the next one): the loop
        link's transform from the current node (the measured one, or the robot's offset moved by
        the hypothesis' offset from its node), the robot's dead-reckoned pose and path, the link's
        information and kernel width (measured or visual)."""
        cfg = self.cfg
        did = len(self._loops.decisions)
        if h.transform is not None:
            link_tr = h.transform
        elif h.offset is None:
            link_tr = self._delta  # the robot stands on the node: the node from the current node is where it is
        else:
            link_tr = _compose3(self._delta, _inv3(h.offset))  # the node from the current node
        if h.information:
            info: tuple[float, ...] = h.information
        elif h.transform is not None:
            info = cfg.loop_information
        elif cfg.visual_lateral_information is None:
            info = cfg.visual_loop_information
        else:  # a visual link is looser beside the robot's heading, which recognition cannot see
            info = (cfg.visual_loop_information[0], cfg.visual_lateral_information, cfg.visual_loop_information[1])
        return Candidate(
            did,
            h.node,
            self._cur,
            link_tr,
            _between3(self._delta, link_tr),
            self._odom,
            self._step,
            self._arrival if h.node == self._cur else -1,
            h.transform is not None,
            self._path,
            tuple(float(v) for v in info),
            cfg.loop_kernel_width if h.transform is not None else cfg.visual_kernel_width,
            h.coupling,
            (h.offset[2] + h.coupling * h.offset[1]) if h.coupling and h.offset is not None else 0.0,
            h.along_sigma,
        )

    def _verify(self, cand: Candidate, t: float) -> LoopDecision:
        """Check (b) of :meth:`propose_loop` for a gated candidate: cycle consistency with the
        pending and accepted candidates of the window; accepted, rejected, or left pending."""
        cfg, book = self.cfg, self._loops
        did = cand.id
        acc, ok_pend, ok_acc = self._cycle_support(cand)
        if ok_acc or (not acc and 1 + len(ok_pend) >= cfg.loop_min_support):
            support = tuple(c.id for c in ok_pend + ok_acc)
            self._accept(ok_pend + [cand], cand, t, support, ok_acc)
            return book.decisions[did]
        if acc:
            ids = ", ".join(str(c.id) for c in acc)
            return self._reject(did, f"contradicts the loop closure(s) accepted within the window: {ids}", t)
        book.pending.append(cand)
        book.decisions[did] = replace(book.decisions[did], support=tuple(c.id for c in ok_pend))
        self._events.append(LoopPending(did, cand.node, cand.from_node, len(ok_pend), t))
        return book.decisions[did]

    def _propose_outside(self, cand: Candidate, t: float, gate_reason: str) -> LoopDecision:
        """A visual hypothesis from a global search (``meta['search'] == 'global'``; from any search with
        ``outside_searches = 'all'``) that names a node outside the gate: after a long excursion the map's
        drift exceeds any gate, so the gate cannot judge it. It waits, without a link, for ``outside_min_support``
        − 1 others of the same kind within ``outside_window_m`` of path that agree with it in space
        (:func:`consistent`: the distance driven between two proposals equals the distance between
        the places they name) and in sequence (the old path between the two named places is as long
        as the path driven between the proposals, within ``loop_consistency_m`` + 10 %); the group
        must then fit one SE(2) transform (:meth:`_fit_group`); one with a member turned beyond a group's heading
        bound must be longer (:meth:`_group_enough`). A fitted group
        becomes verified loop links at weight 1 and the whole map is solved; a lone or
        contradicted hypothesis expires without touching the map."""
        cfg, book, P, S = self.cfg, self._loops, self._P, self._S
        self._expire_outside(t)
        # a turned one (item 130) may join only a long group, which turned ones start: the others group as before
        older = [c for c in book.outside if c.step != cand.step and (cand.turned or not c.turned)]
        # consistent in space, and in sequence: a revisit retraces the old path, so the old path between the two
        # named places (each node's path, plus how far ahead of it the hypothesis puts the robot) is as long as
        # the robot's path between the two proposals
        ok = [
            c
            for c, good in zip(older, consistent(cfg, older, cand, P, S))
            if good
            and abs((S[cand.node] + cand.ahead - S[c.node] - c.ahead) - (cand.path - c.path))
            < cfg.loop_consistency_m + 0.1 * abs(cand.path - c.path)
        ]
        group = self._fit_group(ok + [cand], []) if self._group_enough(ok + [cand]) else None
        if group is None:
            book.outside.append(cand)
            d = replace(
                book.decisions[cand.id],
                reason=f"{gate_reason}: waits for consistent recognitions",
                support=tuple(c.id for c in ok),
            )
            book.decisions[cand.id] = d
            self._events.append(LoopPending(cand.id, cand.node, cand.from_node, len(ok), t))
            return d
        return self._accept_outside(group, cand, gate_reason, t)

    def awaits_long_group(self, decision_id: int) -> bool:
        """Whether hypothesis ``decision_id`` waits for a long group (turned beyond a group's heading bound, item
        130): until one takes it, the mapper treats its key frame as not recognised, as when it was rejected."""
        return any(c.id == decision_id and c.turned for c in self._loops.outside)

    def _group_enough(self, group: list[Candidate]) -> bool:
        """Whether ``group`` is large enough to be fitted: ``outside_min_support`` members, or with a member turned
        beyond a group's heading bound (:attr:`Candidate.turned`) at least ``loop_turned_group`` members spread over
        ``loop_turned_group_m`` of the robot's path (docs/MODEL.md item 130)."""
        cfg = self.cfg
        if not any(c.turned for c in group):
            return len(group) >= cfg.outside_min_support
        paths = [c.path for c in group]
        need = max(cfg.outside_min_support, cfg.loop_turned_group or 0)
        return len(group) >= need and max(paths) - min(paths) >= cfg.loop_turned_group_m

    def _accept_outside(self, group: list[Candidate], cand: Candidate, gate_reason: str, t: float) -> LoopDecision:
        """A fitted group outside the gate (or in its outer part) becomes loop links, each supported by the others;
        the links wait to be judged for retraction (``loop_retract_groups``); the whole map is solved."""
        cfg, book = self.cfg, self._loops
        ids = {c.id for c in group}
        verified = GROUP_VERIFIED + (f", {LONG_GROUP}" if any(c.turned for c in group) else "")
        for c in sorted(group, key=lambda c: c.id):
            link = self._add_loop_link(c)
            if link >= 0:
                self._trust(link)
            sup = tuple(sorted(ids - {c.id}))
            d = book.decisions[c.id]
            why = gate_reason if c.id == cand.id else d.reason  # the others' reasons say why they waited
            where = next((w for w in (OUTER_PART, OBLIQUE) if w in why), "outside the gate")
            book.decisions[c.id] = replace(
                d,
                status="accepted",
                link=link,
                support=sup,
                reason=f"{where}; {verified}",
                decided_step=self._step,
                transform=c.link_tr,
            )
            self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, sup, False, t))
        book.outside = [c for c in book.outside if c.id not in ids]
        book.accepted.extend(group)
        if cfg.loop_retract_groups and cfg.loop_retract_below is not None:  # judged as unverified ones, from now
            book.faded.extend(replace(c, path=self._path) for c in group)
        book.last_verified_path = self._path
        self._events.extend(self._optimise(t))  # the links disagree with the map by far: a whole solve
        return book.decisions[cand.id]

    def _fit_group(self, group: list[Candidate], anchors: list[Candidate]) -> list[Candidate] | None:
        """:func:`~hippomap.loop_pose.fit_group` on the map's poses."""
        return fit_group(group, anchors, self._P, self.cfg)

    def _accept(
        self,
        group: list[Candidate],
        reloc: Candidate,
        t: float,
        support: tuple[int, ...] = (),
        anchors: list[Candidate] | None = None,
    ) -> None:
        """Accept a verified ``group`` (``loop_accept = 'verify'``): its relative pose fitted to
        the ``anchors`` too, a loop link per member, the robot relocalised at ``reloc`` when
        configured, the pending hypotheses settled by the group; then the map is corrected."""
        book = self._loops
        ids = {c.id for c in group}
        group = sorted(self._fit_group(group, anchors or []) or group, key=lambda c: c.id)
        reloc = next(c for c in group if c.id == reloc.id)
        arrival = self._link_group(group, reloc, set(support) | ids, t)
        book.pending = [c for c in book.pending if c.id not in ids]
        book.last_verified_path = self._path
        if self.cfg.loop_relocalise:
            self._set_current(reloc.node, _inv3(reloc.M), t, arrival)
        self._settle_pending(group, ids, t)
        self._events.extend(self._optimise(t))

    def _link_group(self, group: list[Candidate], reloc: Candidate, support: set[int], t: float) -> int:
        """A trusted loop link per member of an accepted group, each supported by the others and
        ``support``; returns the link the robot arrives by at ``reloc``'s node (-1: none)."""
        arrival = -1
        reason = "gate" if self.cfg.loop_min_support <= 1 else "gate and cycle consistency"
        for c in group:
            link = self._add_loop_link(c)
            if link >= 0:
                self._trust(link)
            if c is reloc:
                arrival = link
            note = "" if link >= 0 else "; names the node it was proposed from: robot offset corrected, no link"
            self._record_accepted(c, reason + note, link, tuple(sorted(support - {c.id})), c is reloc, t)
        return arrival

    def _settle_pending(self, group: list[Candidate], ids: set[int], t: float) -> None:
        """The pending hypotheses once ``group`` is accepted: accepted if consistent with a member made at
        another step, else rejected; kept pending if every member was made at its step."""
        contradicted = "contradicted by the accepted loop closure(s) " + ", ".join(map(str, sorted(ids)))
        still = []
        for c in self._loops.pending:
            others = [g for g in group if g.step != c.step]
            if not others:
                still.append(c)
            elif np.any(consistent(self.cfg, others, c, self._P, self._S)):  # the cycle test is symmetric in the pair
                link = self._add_loop_link(c)
                self._record_accepted(c, "supported by an accepted loop closure", link, tuple(sorted(ids)), False, t)
            else:
                self._reject(c.id, contradicted, t)
        self._loops.pending = still

    def _accept_robust(self, cand: Candidate, t: float) -> LoopDecision:
        """``loop_accept = 'robust'``: a hypothesis that passed the gate becomes a loop link at
        once, with the kernel weight of its residual (:func:`~hippomap.robust_kernel.kernel_weights`), revised as
        the map converges. Cycle consistency no longer decides whether a link exists, only whether it is
        *verified*: a verified group has its relative pose fitted, its weights set to 1 and
        relocalises the robot; unverified links can only pull as far as their weight lets them."""
        cfg, book = self.cfg, self._loops
        _, ok_pend, ok_acc = self._cycle_support(cand)  # on the graph without the link under test
        link = self._add_loop_link(cand)
        verified = bool(ok_acc) or 1 + len(ok_pend) >= cfg.loop_min_support
        group = self._fit_group(ok_pend + [cand], ok_acc) if verified else None
        verified = group is not None
        support = tuple(c.id for c in ok_pend + ok_acc)
        reason = "gate; weighted by the robust kernel" + ("; verified by cycle consistency" if verified else "")
        reloc = verified and cfg.loop_relocalise
        self._decide_accepted(cand, reason, link, support, reloc, t)
        if not verified:
            book.pending.append(cand)
        else:
            assert group is not None  # verified
            changed = []
            for c in group:
                k = book.decisions[c.id].link
                if k >= 0 and c.node != c.from_node:
                    self._tr[k] = c.link_tr
                    self._trust(k)
                    changed.append(k)
                    book.decisions[c.id] = replace(book.decisions[c.id], transform=c.link_tr)
            self._link_changed(*changed)
            ids = {c.id for c in group}
            book.pending = [c for c in book.pending if c.id not in ids]
            book.accepted.extend(group)
            book.last_verified_path = self._path
            if reloc:
                c = group[-1]
                self._set_current(c.node, _inv3(c.M), t, link)
        self._events.extend(self._optimise(t))
        return book.decisions[cand.id]

    def _cycle_support(self, cand: Candidate) -> tuple[list[Candidate], list[Candidate], list[Candidate]]:
        """``(accepted, consistent pending, consistent accepted)``: the hypotheses of other steps that the
        cycle test can compare with ``cand`` (:meth:`_comparable`) and, of those, the ones it agrees with
        (:func:`~hippomap.loop_closure.consistent`). Called before ``cand``'s own link exists: a link not
        yet judged must not shorten the leg it is tested across."""
        cfg, book, P, S = self.cfg, self._loops, self._P, self._S
        pend = self._comparable(cand, book.pending)
        acc = self._comparable(cand, book.accepted)
        ok_pend = [c for c, ok in zip(pend, consistent(cfg, pend, cand, P, S)) if ok]
        ok_acc = [c for c, ok in zip(acc, consistent(cfg, acc, cand, P, S)) if ok]
        return acc, ok_pend, ok_acc

    def _comparable(self, cand: Candidate, others: list[Candidate]) -> list[Candidate]:
        """The hypotheses of ``others`` (made at another step) that a cycle test can compare with ``cand``:
        those whose node the map places relative to ``cand``'s well enough for the cycle to mean anything.
        That is, the drift the gate allows (``loop_radius_per_m``) over the path between the two nodes
        through the map's graph is within ``loop_consistency_m``, the cycle's own tolerance. A cycle through
        a leg the map does not know agrees with a hypothesis that repeats the map's error as readily as with
        a true one: it neither supports nor contradicts. The path between the two is bounded below by the
        difference of their graph paths from the robot (triangle inequality); a node the graph does not
        reach (a saved map's, before a closure joins it) keeps the cycle test."""
        others = [c for c in others if c.step != cand.step]
        if not others:
            return []
        g = self.graph_path(np.array([cand.node] + [c.node for c in others], dtype=np.int64))
        with np.errstate(invalid="ignore"):
            far = (
                np.isfinite(g[0])
                & np.isfinite(g[1:])
                & (self.cfg.loop_radius_per_m * np.abs(g[1:] - g[0]) > self.cfg.loop_consistency_m)
            )
        return [c for c, f in zip(others, far.tolist()) if not f]

    def _add_loop_link(self, c: Candidate) -> int:
        """The loop link of an accepted hypothesis ``from_node → node`` with the measured transform.

        A hypothesis may name the node it was proposed from: the robot had already reached that
        node A by online pruning (or an earlier loop) through the *arrival* link prev → A. The
        measurement then says where A is seen from prev: ``arrival ⊕ transform``. An unverified
        prune link is overwritten by it (and becomes a loop link); otherwise a loop link
        prev → A is added. Without an arrival link there is nothing to link (-1): the hypothesis
        only corrects the robot's offset when it relocalises.
        """
        loosen = 1.0 if c.measured else self.cfg.visual_solve_loosening
        if c.node != c.from_node:
            source, tr = c.from_node, c.link_tr
        else:
            k = c.arrival
            if k < 0 or k >= self._m or self._dst[k] != c.node:
                return -1
            source, tr = int(self._src[k]), _compose3(self._tr[k], c.link_tr)
            if self._kind[k] == PRUNE:
                self._tr[k] = tr
                self._kind[k] = LOOP
                self._w[k] = 1.0
                self._set_info(k, c.info, c.along_sigma, loosen)
                self._lkw[k] = c.kernel_width
                self._lcoup[k] = c.coupling
                self._link_changed(k)
                return k
        return self._add_link(
            source,
            c.node,
            tr,
            LOOP,
            0.0,
            allow_duplicate=True,
            info=c.info,
            kernel_width=c.kernel_width,
            coupling=c.coupling,
            along_sigma=c.along_sigma,
            loosen=loosen,
        )
