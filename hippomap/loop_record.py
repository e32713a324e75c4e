"""The record of the map's loop decisions: rejected, accepted, trusted, expired, retracted, reported (spec §4).

The layer of :class:`~hippomap.cognitive_map.CognitiveMap` between its gate (:class:`~hippomap.loop_gate.LoopGate`)
and its loop closing (:class:`~hippomap.loop_closing.LoopClosing`), which decides. Here is what every decision
passes through once made: its entry in the loop book with its event (:meth:`LoopRecord._reject`,
:meth:`LoopRecord._record_accepted`), the trust of a verified link, the expiry of hypotheses that found no
support (:meth:`LoopRecord._expire`), the retraction of links left faded once the map has converged past
them (docs/MODEL.md items 99 and 100), and the reports of the decisions with their links' current weights.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from .loop_closure import Candidate, LoopDecision
from .loop_gate import LoopGate
from .map_events import LoopAccepted, LoopRejected, MapEvent
from .map_graph import LOOP
from .robust_kernel import WEIGHT_FLOOR, is_used

__all__ = ["GROUP_VERIFIED", "RETRACTED", "LoopRecord"]

#: how the reason of a retracted closure (:meth:`LoopRecord._retract_faded`) begins: reports tell them by it
RETRACTED = "retracted"
#: how the reason of a closure accepted with a group of recognitions outside the gate (or in its outer part) ends
GROUP_VERIFIED = "verified by a group of consistent recognitions"


class LoopRecord(LoopGate):
    """The loop book's decisions kept, expired, retracted and reported, over :class:`~hippomap.loop_gate.LoopGate`."""

    @property
    def loop_decisions(self) -> list[LoopDecision]:
        """One decision per proposed hypothesis (index = decision id), latest status."""
        return list(self._loops.decisions)

    @property
    def pending_count(self) -> int:
        """How many hypotheses wait for consistent support."""
        return len(self._loops.pending)

    def _reject(self, did: int, reason: str, t: float) -> LoopDecision:
        d = replace(self._loops.decisions[did], status="rejected", reason=reason, decided_step=self._step)
        self._loops.decisions[did] = d
        self._events.append(LoopRejected(did, d.hypothesis.node, d.from_node, reason, t))
        return d

    def _record_accepted(
        self, c: Candidate, reason: str, link: int, support: tuple[int, ...], relocalised: bool, t: float
    ) -> None:
        """The decision, the event and the book entry of an accepted hypothesis."""
        self._decide_accepted(c, reason, link, support, relocalised, t)
        self._loops.accepted.append(c)

    def _decide_accepted(
        self, c: Candidate, reason: str, link: int, support: tuple[int, ...], relocalised: bool, t: float
    ) -> None:
        """The decision and the event of an accepted hypothesis (its book entry is the caller's)."""
        self._loops.decisions[c.id] = replace(
            self._loops.decisions[c.id],
            status="accepted",
            reason=reason,
            link=link,
            support=support,
            decided_step=self._step,
            transform=c.link_tr,
        )
        self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, support, relocalised, t))

    def _trust(self, k: int) -> None:
        """A verified loop link: weight 1, and (``trust_verified``) out of the kernel's reach,
        so that a true closure is applied fully even where it strains an odometry model that
        claims more precision than it has; only unverified links are weighted down."""
        self._w[k] = 1.0
        if self.cfg.trust_verified:
            self._lkw[k] = np.inf

    def _expire_outside(self, t: float) -> None:
        w = self.cfg.outside_window_m
        for c in self._loops.expired_outside(self._path, w):
            self._reject(c.id, f"outside the gate, and no consistent support within {w:g} m of path", t)

    def _expire(self) -> list[MapEvent]:
        w = self.cfg.loop_support_window_m
        t = self._t if self._t is not None else 0.0
        for c in self._loops.expired(self._path, w):
            if self.cfg.loop_accept == "verified":
                self._reject(c.id, f"expired: no consistent support within {w:g} m of path", t)
            elif self.cfg.loop_retract_below is not None and self._loops.decisions[c.id].status == "accepted":
                self._loops.faded.append(c)
        self._judge_faded(w + self.cfg.loop_retract_after_m, t)
        self._expire_outside(t)
        out, self._events = self._events, []
        return out

    def _judge_faded(self, after_m: float, t: float) -> None:
        """Judge (:meth:`_retract_faded`) the waiting links older than ``after_m`` metres of path that a closure
        verified since they were made could have moved the map towards; the others wait on."""
        book, lv = self._loops, self._loops.last_verified_path
        if lv is None or not book.faded:
            return  # nothing waits, or no closure verified yet: no pass over the list on every update
        due = [c for c in book.faded if self._path - c.path > after_m and lv > c.path]
        if due:
            ids = {c.id for c in due}
            book.faded = [c for c in book.faded if c.id not in ids]
        for c in due:
            self._retract_faded(c.id, after_m, t)

    def _retract_faded(self, did: int, after_m: float, t: float) -> None:
        """An accepted link left unverified over its support window, or made by a group outside the gate
        (``loop_retract_groups``), whose kernel weight is below ``loop_retract_below`` is retracted: held at the
        kernel's floor weight for good (kernel width 0 marks it, and the kernel no longer revises it), its
        decision rejected."""
        bar, d = self.cfg.loop_retract_below, self._loops.decisions[did]
        k = d.link
        linked = d.status == "accepted" and 0 <= k < self._m and self._kind[k] == LOOP
        if bar is None or not linked or not self._w[k] < bar:
            return
        w = float(self._w[k])
        self._w[k] = WEIGHT_FLOOR
        self._lkw[k] = 0.0
        self._link_changed(k)
        kind = "a group's link" if d.reason.endswith(GROUP_VERIFIED) else "unverified"
        self._reject(did, f"{RETRACTED}: {kind}, and faded to weight {w:.3g} after {after_m:g} m of path", t)

    def _link_changed(self, *links: int) -> None:
        """Links ``links`` changed (transform or weight): the solves rebuild; relaxation starts from them."""
        self._version += 1
        self._dirty = True
        self._touched.extend(links)

    def loop_weights(self) -> np.ndarray:
        """The current robust weight of each loop decision's link, indexed by decision id (float64; NaN
        for a decision without a link: pending, rejected, or accepted without one)."""
        w = self._w[: self._m]
        link = np.fromiter((d.link for d in self._loops.decisions), np.int64, len(self._loops.decisions))
        has = (link >= 0) & (link < len(w))
        out = np.full(len(link), np.nan)
        out[has] = w[link[has]]
        return out

    def loop_rows(self) -> list[dict[str, Any]]:
        """Every loop decision as a JSON-ready dict, with the current robust ``weight`` of its
        link (absent without a link) and ``used`` (:func:`~hippomap.robust_kernel.is_used`)."""
        rows = []
        for d, w in zip(self._loops.decisions, self.loop_weights().tolist()):
            row = d.to_dict()
            if not math.isnan(w):
                row["weight"] = w
            row["used"] = is_used(d.status, w)
            rows.append(row)
        return rows
