"""Visual recognition memory driven by visual grid cells (paper §2.2, §3.2; spec §2).

After Bicanski & Burgess (2019, [BBc]), adapted to robot key frames:

* **Learning** (one shot, :meth:`VisualMemory.learn`). The frame is converted to gray,
  resized to ``working_width`` and passed through the retina (:mod:`hippomap.retina`:
  light adaptation, centre-surround, divisive contrast normalisation), so the sensory
  cells see local contrast rather than grey levels ([S]/[BBc]: grey levels stretched by
  ``imadjust``, still available as ``retina_mode="none"``). ``n_fixations`` fixation
  points are chosen (top Shi-Tomasi corners of the stretched grey image, or random points
  as in [S]) and learned in random order. Each becomes a *local feature unit* (feature label
  cell, FLC) whose sensory weights are the Gaussian-tuned response of the sensory cells to
  the *blurred* fovea patch ([S]: "preferred value derived from the blurred image"), whose
  grid-cell weights are the visual-grid-cell code of the fixation point
  (``W_FLC->GC = g(x_k)``; stored as ``x_k`` since ``g`` is a fixed function), and which is
  bidirectionally connected to a new *frame node* (``W_FLC->ID = 1 - U(0, jitter)``,
  ``W_ID->FLC`` its transpose).
* **Recognition** (:meth:`VisualMemory.recognise`) is a saccade sequence ([BBc] main loop,
  spec §2): the first fixation (a query corner) drives the FLCs, which drive competing
  frame hypotheses; the most active frame chooses the next feature; the saccade vector to it is decoded from the
  grid code (Eqs. 4-5, :mod:`hippomap.visual_grid_cells`); a microsaccade snaps the fovea to the best match of the
  predicted patch within ``tolerance_px``; the feature found there (or not) updates the evidence; a frame is accepted
  above ``decision_threshold`` (0.9) once it has also predicted ``verify_saccades`` further features correctly
  (optionally more after resets, ``verify_per_reset``; [S] §3.2: "it will continue to scan"), or once it has crossed
  the threshold in ``repeat_accept`` attempts each reset before their verification was done (docs/MODEL.md item 127);
  an attempt resets after ``max_prediction_errors`` wrong predictions and the query is rejected after ``max_resets``
  resets, or earlier when no frame's activity has reached ``give_up_evidence`` in the first ``give_up_attempts``
  attempts (optionally a bar that grows with the number of competing frames, ``give_up_frames``) or has crossed
  ``decision_threshold`` in the first ``give_up_late_attempts``; optionally it then accepts its place (item 128),
  or, once a place's key frames have kept crossing the threshold, looks at them alone (item 129).

  The grid code is re-anchored onto the first recognised feature (BB's "global
  remapping" for displaced stimuli) and onto every predicted feature, so saccades are the
  *vectors between features* of the learned frame and a revisit seen from a shifted
  viewpoint is still followed (``anchor="none"``: absolute image coordinates, spec §2).

An accepted recognition also reports its image correspondences (query fixation and
matched learned feature, input px) and their robust shift (median, MAD): what the
cognitive map needs to turn a recognition into a relative heading.

Sensory cells: 256 per fovea pixel, ``s_{p,v} = exp(-((I_p - v) / sigma)^2)``, zeroed
below ``sensory_cutoff``. Because an FLC's weights are ``s(I~_k) / sum s(I~_k)``, its drive
``u_k = W_k . s(I)`` reduces exactly to ``sum_p K[I~_{k,p}, I_p] / Z_k`` with the 256 x 256
table ``K = S S^T`` and ``Z_k = sum_p n(I~_{k,p})``: the sensory cells are simulated exactly
but never materialised (961 x 256 per patch).

Scale: every fixation compares the fovea with *all* stored FLCs in one vectorised step.
Above ``index_shortlist + stats_sample`` FLCs an index is used: OpenCV's ``batchDistance``
finds the ``index_shortlist`` nearest 8 x 8 area-averaged patch descriptors among all FLCs
(one call, no Python loop), whose drive is then computed exactly; the mean and standard
deviation of the drive over all FLCs (the ``N_std`` rule) are estimated from the exact
shortlist plus a fixed stratified sample of ``stats_sample`` other units (driven over every
``stats_stride``-th row and column of their foveae, the exact units over every pixel). With
``candidates`` only the candidate frames' FLCs compete, but the statistics stay those of
the whole library (the sensory layer is global; the candidates gate the frame nodes).

Project choices that differ from [BBc]/spec (each a :class:`~hippomap.config.VisualConfig`
field; measured by ``python bench/bench_visual.py --ablation``): ``max_survivors`` 5,
``tolerance_px`` 8, ``next_target="nearest"``, ``prediction_tolerance`` 0.9,
``start_order="strongest"``, ``verify_saccades`` 2, ``anchor="start"``, the retina front
end (``retina_*``) with ``n_std`` 3.3; plus the FLC index (``index_*``, ``stats_sample``, ``stats_stride``)
for scale.

The module's parts: frames to working images (:mod:`hippomap.visual_images`), the feature store,
its drive and index (:mod:`hippomap.feature_store`), the recognition records
(:mod:`hippomap.visual_recognition`), their drawing (:mod:`hippomap.visual_drawing`), what one
fixation senses: the FLC drive and pruning, the decoded saccade vector, the microsaccade
(:mod:`hippomap.visual_fixation`); this module holds the saccade loop (:class:`VisualMemory`) and
re-exports the public names of the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from .errors import InputError, finite
from .feature_store import STATE_VERSION, FlcSubset
from .retina import imadjust as _imadjust  # noqa: F401  (kept importable from here)
from .visual_drawing import draw_frame_features, draw_trace
from .visual_fixation import FixationSensing, Sense
from .visual_images import prepare_image, prepare_views
from .visual_recognition import (
    PLACE_ACCEPTED,
    PLACE_LOOKED,
    Crossing,
    Recognition,
    SaccadeStep,
    correspondences,
    place_choice,
    shift_summary,
)
from .visual_recognition import leading as _leading

__all__ = [
    "VisualMemory",
    "Recognition",
    "shift_summary",
    "SaccadeStep",
    "prepare_image",
    "prepare_views",
    "draw_trace",
    "draw_frame_features",
    "STATE_VERSION",
]


@dataclass
class _Attempt:
    """The state of one recognition attempt: from its start fixation to an accept or a reset."""

    e: np.ndarray  # eye position on the query (working px)
    m: np.ndarray  # grid-cell position on the view plane (memory coordinates)
    predicted: int = -1  # global FLC index predicted at this fixation
    target: np.ndarray | None = None
    n_sacc: int = 0
    confirmed: int = 0
    pred_err: int = 0
    verify_left: int = -1  # saccades left to verify a hypothesis past the threshold (-1: not verifying)
    accepted_frame: int = -1
    reset_reason: str | None = None
    first: bool = True
    visited: list[int] = field(default_factory=list)
    primed: float = 0.0  # the frame activity the attempt started with, summed (the prior; not evidence)

    def crossing(self, a: np.ndarray, attempt: int) -> Crossing:
        """The attempt's threshold crossing: its accepted frame, ``attempt``, that frame's activity in ``a``."""
        return Crossing(self.accepted_frame, attempt, float(a[self.accepted_frame]), self.confirmed)


@dataclass
class _Query:
    """A query ready for the saccade loop: the competing feature units, the image the fovea
    senses (working px), the start corners, the working-to-input scale and the input size."""

    sub: FlcSubset
    sense_img: np.ndarray
    starts: np.ndarray
    scale: float
    size: tuple[int, int]
    nframes: int  # the frames competing
    prior: np.ndarray  # each frame's activity at the start of every attempt (zeros without a prior)
    reason: str = "accepted"  # Recognition.reason of a frame accepted among these units


def _check_bar(value: Any) -> float:
    """A give-up bar passed to :meth:`VisualMemory.recognise`: a number in (0, 1], else :class:`InputError`."""
    bar = finite("give_up_evidence", value)
    if not 0.0 < bar <= 1.0:
        raise InputError(f"give_up_evidence must be in (0, 1], got {value!r}")
    return bar


class VisualMemory(FixationSensing):
    """Library of key frames learned one-shot, recognised by saccade sequences (paper §2.2).

    >>> mem = VisualMemory()                      # doctest: +SKIP
    >>> fid = mem.learn(frame)                    # int, or None if the frame has < min_fixations corners
    >>> rec = mem.recognise(other_frame)          # Recognition; rec.frame_id is None if rejected
    >>> rec = mem.recognise(other_frame, candidates=[3, 4, 9])
    """

    # -- recognition -------------------------------------------------------------------
    def recognise(
        self,
        image: Any,
        candidates: Iterable[int] | None = None,
        give_up_evidence: float | None = None,
        prior: Iterable[int] | None = None,
        prior_activity: float = 0.0,
    ) -> Recognition:
        """Recognise a frame by a saccade sequence (spec §2 recognition; [BBc] main loop).

        ``candidates``: the frame ids whose hypotheses compete (the map passes the key frames near its place code);
        ``None`` = all. ``give_up_evidence``: this recognition's bar of the give-up rule (``None``: the config's,
        :meth:`_give_up_bar`; a search among more frames can ask more). ``prior``: candidate frames expected here
        (:attr:`~hippomap.config.MapperConfig.sequence_prior`), which start every attempt at ``prior_activity`` (in
        [0, ``decision_threshold``)): they still compete and must be verified; the head start counts towards neither
        the give-up bars nor ``max_total_activity``.

        Attempts (:meth:`_attempt`, each from a query corner, :meth:`_start_point`) follow each other until one
        accepts a frame, ``max_resets`` resets are used or a give-up rule ends them (:meth:`_given_up`); once a
        place's frames have kept crossing the threshold, the next attempts may look at them alone
        (:meth:`_place_look`). At every fixation (:meth:`_fixate`) the feature units are driven (:meth:`_sense`), the
        hypotheses updated (:meth:`_observe`), the decision checked (:meth:`_decide`) and the most active frame
        chooses the next saccade (:meth:`_next_saccade`).
        """
        cfg = self.config
        bar = None if give_up_evidence is None else _check_bar(give_up_evidence)
        q = self._query(image, candidates, prior, prior_activity)
        if isinstance(q, Recognition):
            return q
        if bar is None:
            bar = self._give_up_bar(q.nframes)
        a = np.zeros(self._nframes, np.float64)
        primed = float(q.prior.sum())
        steps: list[SaccadeStep] = []
        used_starts: set[int] = set()
        peak = 0.0  # the highest frame activity of any attempt so far (activity only grows within one)
        crossed: list[Crossing] = []  # frames that crossed the threshold and failed verification, attempt by attempt
        look: _Query | None = None  # the place's frames alone, once they have kept crossing (docs/MODEL.md item 129)
        looks = 0
        for resets in range(cfg.max_resets + 1):
            a[:] = q.prior
            e = self._start_point(q.starts, used_starts)
            st = _Attempt(e=e, m=e.copy(), primed=primed)
            accepted = self._attempt(look or q, st, a, steps, resets)
            if accepted is None and look is None:
                accepted = self._repeated(q, st, a, steps, resets, crossed)
            if accepted is not None:
                return accepted
            steps[-1].event = f"reset: {st.reset_reason}"
            best = float((a - q.prior).max()) if a.size else 0.0
            peak = max(peak, best)
            looks += look is not None
            look = look or self._place_look(crossed, q)
            why = self._given_up(resets + 1, peak, bar, looks)
            if why:
                break
        else:
            why = f"no match after {cfg.max_resets} resets"
        return self._placed(crossed, q, steps, resets) or Recognition(None, best, steps, resets, 0.0, q.size, why)

    def _query(
        self, image: Any, candidates: Iterable[int] | None, prior: Iterable[int] | None, prior_activity: float
    ) -> _Query | Recognition:
        """The query's views, the competing feature units and each frame's starting activity
        (:meth:`_prior`), or the rejection when there is nothing to recognise (no stored frame among the
        candidates, no corner in the query)."""
        cfg = self.config
        work, scale, cimg = self._views(image)
        H, W = work.shape[:2]
        size = (int(round(W * scale)), int(round(H * scale)))
        frames = None if candidates is None else self._candidate_frames(candidates)
        start = self._prior(frames, prior, prior_activity)
        sub = FlcSubset(self, frames)
        if sub.n == 0:
            return Recognition(None, 0.0, [], 0, 0.0, size, "no stored frames")
        sense_img = self._blur(work) if cfg.query_blur else work
        starts = self._corners(cimg, cfg.query_keypoints, self.h)
        if len(starts) == 0:
            return Recognition(None, 0.0, [], 0, 0.0, size, "no keypoints in the query")
        nframes = self._nframes if frames is None else int(frames.size)
        return _Query(sub, sense_img, starts, scale, size, nframes, start)

    def _prior(self, frames: np.ndarray | None, prior: Iterable[int] | None, activity: float) -> np.ndarray:
        """Each frame's activity at the start of an attempt: ``activity`` for the ``prior`` frames, 0 for the
        others. The prior frames must be stored frames among the candidates (``frames``; None: all) and the
        activity a number in [0, ``decision_threshold``): a head start, never a decision."""
        start = np.zeros(self._nframes, np.float64)
        if prior is None:
            return start
        a = finite("prior_activity", activity)
        if not 0.0 <= a < self.config.decision_threshold:
            raise InputError(f"prior_activity must be in [0, {self.config.decision_threshold:g}), got {a:g}")
        ids = self._candidate_frames(prior)
        if frames is not None and (outside := np.setdiff1d(ids, frames)).size:
            raise InputError(f"prior frames must be among the candidates; not candidates: {outside[:5].tolist()}")
        start[ids] = a
        return start

    def _given_up(self, attempts: int, peak: float, bar: float, looks: int) -> str:
        """Why a recognition gives up after ``attempts`` attempts whose highest frame activity was ``peak``, or "":
        no frame reached ``bar`` in the first ``give_up_attempts``, or none crossed ``decision_threshold`` in the
        first ``give_up_late_attempts`` (an evidence-accumulation bound that collapses with time), or ``looks``
        attempts among a place's frames alone verified none (``place_look``)."""
        cfg = self.config
        if cfg.place_look is not None and looks >= cfg.place_look:
            return f"its place not verified in {looks} attempts"
        if cfg.give_up_attempts is not None and attempts >= cfg.give_up_attempts and peak < bar:
            return f"no frame reached {bar:g} in {attempts} attempts"
        late = cfg.give_up_late_attempts
        if late is not None and attempts >= late and peak <= cfg.decision_threshold:
            return f"no frame crossed {cfg.decision_threshold:g} in {attempts} attempts"
        return ""

    def _give_up_bar(self, nframes: int) -> float:
        """The give-up bar of a recognition among ``nframes`` competing frames: ``give_up_evidence``, or with
        ``give_up_frames = (n0, n1)`` a bar that grows with the log of the count from ``give_up_evidence`` (at n0
        frames or fewer) to ``decision_threshold`` (at n1 or more): the best of many frames reaches more by
        chance alone, so a search among many must show more in its first attempts to be worth the rest."""
        cfg = self.config
        if cfg.give_up_frames is None or nframes <= cfg.give_up_frames[0]:
            return cfg.give_up_evidence
        n0, n1 = cfg.give_up_frames
        f = min(1.0, math.log(nframes / n0) / math.log(n1 / n0))
        return cfg.give_up_evidence + (cfg.decision_threshold - cfg.give_up_evidence) * f

    def _candidate_frames(self, candidates: Iterable[int]) -> np.ndarray:
        """The distinct candidate frame ids, sorted: ``np.unique`` of every candidate checked by
        :meth:`_check_frame`. A list of integers all in range (what the mapper passes) is checked as one
        array, with the same ids; anything else goes through :meth:`_check_frame` one by one, which
        converts what it accepts and names what it rejects."""
        if isinstance(candidates, list) and candidates:
            try:
                arr = np.array(candidates)
            except (TypeError, ValueError, OverflowError):
                arr = None
            if (
                arr is not None
                and arr.ndim == 1
                and arr.dtype.kind in "iu"
                and int(arr.min()) >= 0
                and int(arr.max()) < self._nframes
            ):
                return np.unique(arr.astype(np.int64))
        return np.unique(np.array([self._check_frame(c) for c in candidates], dtype=np.int64))

    def _attempt(
        self, q: _Query, st: _Attempt, a: np.ndarray, steps: list[SaccadeStep], resets: int
    ) -> Recognition | None:
        """One attempt, fixation after fixation, from its start point: the recognition when it
        accepts a frame, None when it resets (its reason in ``st.reset_reason``)."""
        while True:
            s, outcome = self._fixate(q, st, a, steps, resets)
            self._decide(st, outcome, steps, a, resets)
            if st.reset_reason is None and st.verify_left == 0:
                return self._accepted(st.crossing(a, resets), steps, resets, q.size, q.reason)
            if not self._next_saccade(st, s, q.sub, a, q.sense_img):
                return None

    def _fixate(
        self, q: _Query, st: _Attempt, a: np.ndarray, steps: list[SaccadeStep], resets: int
    ) -> tuple[Sense, str]:
        """One fixation: the feature units are driven at the eye position, the frame hypotheses
        updated, and the step recorded in the trace; returns what was sensed and the outcome."""
        sub, pred, scale = q.sub, st.predicted, q.scale
        s = self._sense(q.sense_img, st.e, sub, sub.local(pred) if pred >= 0 else -1)
        outcome, found = self._observe(st, s, sub, a)
        # points in input px: the float of each integer coordinate times the scale (the eye and the target are
        # integer arrays: tolist gives the integers indexing them gives)
        ex, ey = st.e.tolist()
        tgt = st.target
        if tgt is not None:
            tx, ty = tgt.tolist()
        steps.append(
            SaccadeStep(
                resets,
                (float(ex) * scale, float(ey) * scale),
                None if tgt is None else (float(tx) * scale, float(ty) * scale),
                int(self._frame[pred]) if pred >= 0 else None,
                None if pred < 0 else int(pred),
                None if found is None else int(self._frame[found]),
                found,
                float(s.umax),
                outcome,
                _leading(a, self.config.trace_hypotheses),
            )
        )
        st.first = False
        return s, outcome

    def _repeated(
        self, q: _Query, st: _Attempt, a: np.ndarray, steps: list[SaccadeStep], resets: int, crossed: list[Crossing]
    ) -> Recognition | None:
        """After an attempt that reset past the threshold: the crossing recorded in ``crossed`` (never a primed
        frame's) and its frame accepted once it has crossed in ``repeat_accept`` attempts (docs/MODEL.md item 127)."""
        f, k = st.accepted_frame, self.config.repeat_accept
        if f < 0 or q.prior[f]:
            return None
        crossed.append(st.crossing(a, resets))
        if not k or sum(c.frame == f for c in crossed) < k:
            return None
        return self._accepted(crossed[-1], steps, resets, q.size, q.reason)

    def _placed(self, cs: list[Crossing], q: _Query, steps: list[SaccadeStep], resets: int) -> Recognition | None:
        """The :class:`Recognition` of a recognition about to end without a frame: its place, the most active
        crossing's frame, once frames learned within ``place_span`` of it have crossed in ``place_accept`` of its
        attempts (``cs``; :func:`place_choice`, docs/MODEL.md item 128); else None."""
        n = self.config.place_accept
        at = place_choice(cs, n, self.config.place_span, self.config.place_confirmed) if n else None
        return None if at is None else self._accepted(at, steps, resets, q.size, PLACE_ACCEPTED)

    def _place_look(self, cs: list[Crossing], q: _Query) -> _Query | None:
        """The query among its place's frames alone (the candidates learned within ``place_span`` of the most active
        crossing's frame), once such frames have crossed in ``place_look_crossings`` of its attempts (``cs``;
        :func:`place_choice`), if ``place_look`` is set; else None (docs/MODEL.md item 129)."""
        cfg = self.config
        n, distinct = cfg.place_look_crossings, cfg.place_look_distinct
        at = place_choice(cs, n, cfg.place_span, cfg.place_confirmed, distinct) if cfg.place_look else None
        if at is None:
            return None
        frames = np.unique(self._frame[q.sub.idx]).astype(np.int64)
        frames = frames[np.abs(frames - at.frame) <= cfg.place_span]
        sub = FlcSubset(self, frames)
        return _Query(sub, q.sense_img, q.starts, q.scale, q.size, int(frames.size), q.prior, PLACE_LOOKED)

    def _accepted(
        self, at: Crossing, steps: list[SaccadeStep], resets: int, size: tuple[int, int], reason: str
    ) -> Recognition:
        """The recognition of crossing ``at`` (the accepting attempt's, or an earlier one's): its confidence (the
        fraction of confirmed predictions, discounted by the resets needed) and that attempt's correspondences."""
        steps[-1].event = "accept"
        n_att = sum(1 for x in steps if x.attempt == at.attempt)
        conf = (at.confirmed + 1) / max(1, n_att) / (1.0 + resets)
        scale = float(self._fscale[at.frame])
        corr, shift = correspondences(steps, at.attempt, at.frame, self._frame, self._pos, scale)
        return Recognition(at.frame, at.activity, steps, resets, float(conf), size, reason, corr, shift)

    def _start_point(self, starts: np.ndarray, used_starts: set[int]) -> np.ndarray:
        """The first fixation of a new attempt (working px): a query corner not used yet by this
        recognition (all again once each has been used), the strongest or a random one."""
        free = [i for i in range(len(starts)) if i not in used_starts]
        if not free:
            used_starts.clear()
            free = list(range(len(starts)))
        si = int(free[int(self._rng.integers(len(free)))]) if self.config.start_order == "random" else int(min(free))
        used_starts.add(si)
        return starts[si].astype(np.int64)

    def _observe(self, st: _Attempt, s: Sense, sub: FlcSubset, a: np.ndarray) -> tuple[str, int | None]:
        """``(outcome, found feature)`` of a fixation, and its effect on the attempt: the frame
        hypotheses ``a`` gain the survivors' weights ([BBc]), a wrong prediction counts towards
        a reset, the first feature found re-anchors the grid code (``anchor = 'start'``)."""
        cfg = self.config
        if not s.evidence:
            if st.first:
                st.reset_reason = "first fixation not informative"
            return "no_evidence", None
        found = int(sub.idx[s.winner])
        if st.first:
            outcome = "start"
        elif found == st.predicted or (st.predicted >= 0 and s.upred >= cfg.prediction_tolerance * s.umax):
            outcome = "confirmed"
            st.confirmed += 1
        else:
            outcome = "mismatch"
            st.pred_err += 1
            if st.pred_err > cfg.max_prediction_errors:
                st.reset_reason = "too many wrong predictions"
        if st.reset_reason is None and (outcome != "mismatch" or cfg.update_on_mismatch):
            assert s.weights is not None  # a fixation with evidence has its survivors' weights
            g = sub.idx[s.survivors]
            # np.add.at(a, frames, gains) then np.clip(a, 0, 1, out=a), on the few survivors' frames: the same
            # double additions in the same order (a frame met twice adds twice, in survivor order), and the
            # clip of the changed entries only, which is np.clip's own rule (below 0 -> 0, above 1 -> 1, else
            # the value: -0.0 and NaN kept): every other entry was clipped before and a clip changes no
            # clipped value
            frames = self._frame[g].tolist()
            for f, v in zip(frames, (cfg.kappa * self._w[g] * s.weights).tolist()):
                a[f] += v
            for f in frames:
                x = a[f]
                if x < 0.0:
                    a[f] = 0.0
                elif x > 1.0:
                    a[f] = 1.0
            if np.add.reduce(a) - st.primed > cfg.max_total_activity:  # a.sum(): the same reduction
                st.reset_reason = "total frame activity too high"
            if st.first and cfg.anchor == "start":
                st.m = self._pos[found].astype(np.int64)  # global remapping onto the feature
        return outcome, found

    def _decide(self, st: _Attempt, outcome: str, steps: list[SaccadeStep], a: np.ndarray, resets: int) -> None:
        """The decision after a fixation: a verification saccade must confirm its prediction; a
        frame above ``decision_threshold`` is accepted once it has predicted ``verify_saccades``
        more features (more after resets: every reset is another chance for a wrong frame)."""
        cfg = self.config
        if st.reset_reason is None and st.verify_left > 0:
            if outcome == "confirmed":  # the accepted frame predicted this feature
                st.verify_left -= 1
            else:
                st.reset_reason = "verification saccade failed"
        if st.reset_reason is None and st.verify_left < 0 and a.max() > cfg.decision_threshold:
            st.accepted_frame = int(np.argmax(a))
            # every reset is another chance for a wrong frame: later attempts must verify more
            st.verify_left = cfg.verify_saccades + int(resets * cfg.verify_per_reset)
            if st.verify_left > 0:
                steps[-1].event = "threshold"

    def _next_saccade(self, st: _Attempt, s: Sense, sub: FlcSubset, a: np.ndarray, img: np.ndarray) -> bool:
        """Choose the next target (the most active frame chooses, :meth:`_choose_target`) and move
        the eye and the grid code there; False (with the attempt's reset reason) when none is left."""
        cfg = self.config
        if st.reset_reason is None:
            cur = int(sub.idx[s.top]) if s.evidence else st.predicted
            if cur >= 0:
                if len(st.visited) >= cfg.n_fixations - 1:
                    st.visited = [st.visited[-1], cur]
                else:
                    st.visited.append(cur)
            if st.n_sacc >= cfg.max_saccades:
                st.reset_reason = "saccade cap reached"
        if st.reset_reason is not None:
            return False
        k_star, tgt, land, why = self._choose_target(
            a, st.e, st.m, st.visited, self._rng, img, st.accepted_frame if st.verify_left > 0 else -1
        )
        if k_star < 0:
            st.reset_reason = why
            return False
        st.n_sacc += 1
        st.target = tgt
        st.e = land.astype(np.int64)
        st.m = self._pos[k_star].astype(np.int64) if cfg.anchor == "start" else st.e.copy()
        st.predicted = k_star
        return True
