"""What the visual memory senses at one fixation (paper §2.2; spec §2 steps 3-7; [BBc]).

At a fixation the fovea drives the feature label cells (FLCs): their drive, the [BBc]
evidence test ``max u > mean + N_std sd`` and the pruning to a few survivors with softmax
weights (:meth:`FixationSensing._sense`). A saccade to a predicted feature is the vector
decoded from the visual grid cells' codes of the gaze and the feature's learned position
(Eqs. 4-5, :mod:`hippomap.visual_grid_cells`), and the microsaccade snaps the landing point
to the best match of the predicted patch (:meth:`FixationSensing._microsaccade`); the most active
frame chooses which of its features to look at next (:meth:`FixationSensing._choose_target`). The saccade
loop that strings fixations into a recognition is :class:`hippomap.visual_memory.VisualMemory`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .config import VisualConfig
from .feature_store import FeatureStore, FlcSubset, _channel0
from .visual_grid_cells import SpatialViewCells, VisualGridCells

_DECODE_CACHE = 1 << 15  # decoded saccade vectors remembered per memory (a few MB at most)


@dataclass
class Sense:
    """What the FLC population reports at one fixation (local indices into the subset)."""

    evidence: bool
    winner: int  # local index of argmax u (valid even without evidence)
    umax: float
    survivors: np.ndarray | None = None  # local indices
    weights: np.ndarray | None = None  # softmax weights of the survivors
    top: int = -1  # argmax of the biased, pruned vector (local)
    upred: float = 0.0  # drive of the predicted unit


class FixationSensing(FeatureStore):
    """The feature store with the senses of a fixation: the FLC drive and pruning, the decoded
    saccade vector and the microsaccade (the saccade loop is :class:`~hippomap.visual_memory.VisualMemory`)."""

    def __init__(self, config: VisualConfig | None = None):
        super().__init__(config)
        self.grid = VisualGridCells(self.config)
        self._svc: SpatialViewCells | None = None
        self._decoded: dict[bytes, np.ndarray] = {}  # see _decode_shared
        self._phase_codes: dict[bytes, np.ndarray] = {}  # see _phase_code

    # -- saccade vectors -----------------------------------------------------------------
    @property
    def spatial_view_cells(self) -> SpatialViewCells:
        """Spatial view cells over the working view plane (built on first use)."""
        if self._svc is None:
            cfg = self.config
            self._svc = SpatialViewCells(self.grid, cfg.working_width, cfg.working_width, cfg.svc_stride)
        return self._svc

    def _decode(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Saccade vector from gaze ``m`` to ``target`` decoded from their grid codes (a fresh array)."""
        return self._decode_shared(np.asarray(m, dtype=float), np.asarray(target, dtype=float)).copy()

    def _decode_shared(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        """:meth:`_decode` of two float points, the remembered array itself (read only).

        Both points are whole pixels during a recognition (learned positions, fovea positions), and
        the decoded vector is a fixed function of the two points, so it is remembered per pair: the
        same candidate frames come back recognition after recognition with the same feature pairs."""
        key = m.tobytes() + target.tobytes()  # bytes, so that even -0.0 and 0.0 stay apart
        d = self._decoded.get(key)
        if d is None:
            if len(self._decoded) >= _DECODE_CACHE:
                self._decoded.clear()
                self._phase_codes.clear()
            d = self._decode_uncached(m, target)
            d.flags.writeable = False
            self._decoded[key] = d
        return d

    def _decode_uncached(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        if self.config.decoder == "svc":
            return self.spatial_view_cells.decode(self.grid.encode(m), self.grid.encode(target))
        # VisualGridCells.decode(encode(m), encode(target)), step by step: each point's module phasors
        # (its grid code's Fourier projection) are remembered, since a point comes back in many pairs
        zf, zt = self._phase_code(m), self._phase_code(target)
        w = zt * np.conj(zf)
        # np.angle(w) is arctan2(w.imag, w.real) for a complex array, and decode_phase_difference of one
        # (M, 3) float difference is _decode_one: the same calls without their wrappers
        return self.grid._decode_one(np.arctan2(w.imag, w.real))

    def _phase_code(self, p: np.ndarray) -> np.ndarray:
        """The module phasors of point ``p``'s grid code (``grid._project(grid.encode(p))``, read only):
        a fixed function of the point, remembered per point (cleared with the decoded pairs)."""
        key = p.tobytes()
        z = self._phase_codes.get(key)
        if z is None:
            if len(self._phase_codes) >= _DECODE_CACHE:
                self._phase_codes.clear()
            z = self.grid._phase_code_one(p)
            z.flags.writeable = False
            self._phase_codes[key] = z
        return z

    # -- sensing -----------------------------------------------------------------------
    def _sense(self, img: np.ndarray, pos: np.ndarray, sub: FlcSubset, predicted: int) -> Sense:
        """Drive of the FLC population at fixation ``pos`` and the [BBc] pruning: evidence test
        ``max u > mean + N_std sd``, ``u / max u``, bias on the predicted unit, prune, softmax."""
        cfg = self.config
        x, y = int(pos[0]), int(pos[1])
        patch = self._patch_at(img, x, y)
        T, uT, uR = self._shortlist_drive(patch, x, y, sub, predicted)
        mean, var, N = self._drive_stats(sub, T, uT, uR)
        j = int(uT.argmax())
        umax = float(uT[j])
        winner = int(T[j])
        # position of the predicted unit among the scored ones (T is 0..n-1 without the index)
        p = -1
        if predicted >= 0:
            if T is sub.all_local:
                p = predicted
            else:
                pk = (T == predicted).nonzero()[0]  # np.flatnonzero of a 1-D array
                p = int(pk[0]) if pk.size else -1
        upred = float(uT[p]) if p >= 0 else 0.0
        if not umax > mean + cfg.n_std * math.sqrt(var) or umax <= 0:
            return Sense(False, winner, umax, upred=upred)
        # normalise, bias the predicted unit, prune at mean + N_std sd, softmax ([BBc])
        ut = uT / umax  # a new array: the bias below never touches the (remembered) drive
        mean_t, var_t = mean / umax, var / umax**2
        if p >= 0:
            old = float(ut[p])
            ut[p] = old * cfg.prediction_bias
            m2_t = var_t + mean_t**2 + (ut[p] ** 2 - old**2) / N
            mean_t = mean_t + (ut[p] - old) / N
            var_t = max(0.0, m2_t - mean_t**2)
        # the survivors as ascending positions in T (what the boolean mask T[keep] selects, in its order)
        sel = (ut >= mean_t + cfg.n_std * math.sqrt(var_t)).nonzero()[0]
        if sel.size == 0:
            sel = np.array([int(ut.argmax())])
        if cfg.max_survivors and sel.size > cfg.max_survivors:
            # spec §6.4: N_std must grow with the library so that 1-5 FLCs survive; a top-K cap
            # does that for every library size (the K strongest, stable among ties, back in ascending order)
            sel = np.sort(sel[(-ut[sel]).argsort(kind="stable")[: cfg.max_survivors]])
        surv = sel if T is sub.all_local else T[sel]  # T[sel] = sel when T is 0..n-1
        vals = ut[sel].astype(np.float64) * cfg.softmax_gain
        e = np.exp(vals - np.maximum.reduce(vals))
        wts = e / np.add.reduce(e)  # e.sum(): the same reduction
        best = int(surv[int(vals.argmax())])
        return Sense(True, winner, umax, surv, wts, best, upred)

    def _microsaccade(self, img: np.ndarray, target: np.ndarray, flc: int, amplitude: float = 0.0) -> np.ndarray | None:
        """Snap the landing point to the best match of the predicted feature within ``tolerance_px``
        plus ``microsaccade_gain`` x the saccade's ``amplitude`` (the [BBc] microsaccade; the search
        widens with the amplitude as saccadic endpoint scatter does); ``None`` if the fovea cannot be
        placed inside the image."""
        h = self.h
        r = self.config.tolerance_px + int(round(self.config.microsaccade_gain * amplitude))
        img = _channel0(img)  # the microsaccade matches the ganglion fovea
        H, W = img.shape
        lo_x, hi_x = h, W - h - 1
        lo_y, hi_y = h, H - h - 1
        tx, ty = int(target[0]), int(target[1])
        x0, x1 = max(lo_x, tx - r), min(hi_x, tx + r)
        y0, y1 = max(lo_y, ty - r), min(hi_y, ty + r)
        if x0 > x1 or y0 > y1:
            return None
        if r == 0:
            return np.array([x0, y0])
        tmpl = self._patch[flc, : self.P0].reshape(self.config.fovea, self.config.fovea)
        if r > self.config.tolerance_px and min(x1 - x0, y1 - y0) > 4:
            # a wide search runs coarse to fine: on the half-resolution fovea first (a quarter of the
            # pixels per match and a quarter of the positions), then +-2 px around it at full resolution
            region = img[y0 - h : y1 + h + 1, x0 - h : x1 + h + 1]
            half = (region.shape[1] // 2, region.shape[0] // 2)
            th = (tmpl.shape[1] // 2, tmpl.shape[0] // 2)
            res = cv2.matchTemplate(
                cv2.resize(region, half, interpolation=cv2.INTER_AREA),
                cv2.resize(tmpl, th, interpolation=cv2.INTER_AREA),
                cv2.TM_SQDIFF,
            )
            _, _, loc, _ = cv2.minMaxLoc(res)
            cx, cy = x0 + 2 * loc[0], y0 + 2 * loc[1]
            x0, x1 = max(x0, cx - 2), min(x1, cx + 2)
            y0, y1 = max(y0, cy - 2), min(y1, cy + 2)
        region = img[y0 - h : y1 + h + 1, x0 - h : x1 + h + 1]
        res = cv2.matchTemplate(region, tmpl, cv2.TM_SQDIFF)
        _, _, loc, _ = cv2.minMaxLoc(res)
        return np.array([x0 + loc[0], y0 + loc[1]])

    # -- the next saccade's target --------------------------------------------------------
    def _choose_target(
        self,
        a: np.ndarray,
        e: np.ndarray,
        m: np.ndarray,
        visited: list[int],
        rng: np.random.Generator,
        img: np.ndarray,
        frame: int = -1,
    ) -> tuple[int, Any, Any, str]:
        """Next feature k* chosen by the frame hypotheses, its saccade vector decoded from the
        grid code, and the landing point after the microsaccade (spec §2 steps 5-7).

        Returns ``(k*, target, landing, "")`` or ``(-1, None, None, reason)`` for a reset.
        """
        cfg = self.config
        active = np.flatnonzero(a > 0)
        if active.size == 0:
            return -1, None, None, "no frame hypothesis"
        if frame >= 0:  # verification: the accepted frame predicts
            active = np.array([frame])
        elif cfg.next_target != "stochastic":
            active = active[[int(np.argmax(a[active]))]]
        if cfg.next_target == "nearest":  # one frame chooses, among its few features
            return self._nearest_target(int(active[0]), e, m, visited, img)
        ks, v = self._target_preferences(a, active, visited, rng)
        order = np.argsort(-v, kind="stable")
        order = order[v[order] > 0][: cfg.target_candidates]
        return self._land_first(ks[order].tolist(), e, m, img)

    def _nearest_target(
        self, f: int, e: np.ndarray, m: np.ndarray, visited: list[int], img: np.ndarray
    ) -> tuple[int, Any, Any, str]:
        """:meth:`_choose_target` with ``next_target = 'nearest'`` once frame ``f`` chooses: its unvisited
        features by preference ``1 / (1 + |dx| + |dy|)`` to the gaze ``m`` (whole pixels), strongest first,
        ties in feature order, on Python scalars for its few features (numpy's call overhead would cost more
        than the arithmetic)."""
        cfg = self.config
        f0 = int(self._fstart[f])
        pos = self._pos[f0 : f0 + int(self._fcount[f])]
        mx, my = m.tolist()
        v = [1.0 / (1.0 + (abs(px - mx) + abs(py - my))) for px, py in pos.tolist()]
        n = len(v)
        for k in visited:
            if f0 <= k < f0 + n:
                v[k - f0] = 0.0
        order = sorted([j for j in range(n) if v[j] > 0], key=lambda j: -v[j])[: cfg.target_candidates]
        return self._land_first([f0 + j for j in order], e, m, img)

    def _land_first(
        self, features: list[int], e: np.ndarray, m: np.ndarray, img: np.ndarray
    ) -> tuple[int, Any, Any, str]:
        """The first of ``features`` (best first; usually the first is taken) whose saccade vector, decoded
        from the grid codes of the gaze ``m`` and the feature's learned position, leaves the tolerance and
        whose landing the microsaccade finds: ``(k*, target, landing, "")``, or ``(-1, None, None, reason)``
        for a reset. Both decoders return whole pixels (int64)."""
        cfg = self.config
        tol, gain = cfg.tolerance_px, cfg.microsaccade_gain
        mf = m.astype(float)
        for k in features:
            d = self._decode_shared(mf, self._pos[k].astype(float))  # decode(g(m), W_FLC->GC e_k), int64
            dx, dy = d.tolist()
            if abs(dx) <= tol and abs(dy) <= tol:
                continue  # [BBc]: choose again while the vector is within tolerance
            tgt = e + d
            # the amplitude only widens the search by microsaccade_gain x amplitude: without a gain that is
            # round(0.0 x a finite amplitude) = 0 whatever the amplitude, so it is not computed
            amp = float(np.hypot(dx, dy)) if gain else 0.0
            land = self._microsaccade(img, tgt, k, amp)
            if land is None:
                if cfg.out_of_view == "skip":
                    continue  # the predicted feature lies outside this view: look at another one
                return -1, None, None, "saccade out of the image"
            return k, tgt, land, ""
        return -1, None, None, "no feature left to predict"

    def _target_preferences(
        self, a: np.ndarray, active: np.ndarray, visited: list[int], rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(ks, v)``: the features of the choosing frames ``active`` and each one's preference as the next
        target (``next_target``), 0 for the features visited in this attempt."""
        cfg = self.config
        if active.size == 1:  # one frame chooses (always unless stochastic): its features are one range
            f0 = int(self._fstart[active[0]])
            ks = np.arange(f0, f0 + int(self._fcount[active[0]]))
        else:
            ks = np.concatenate([np.arange(self._fstart[f], self._fstart[f] + self._fcount[f]) for f in active])
        if cfg.next_target == "stochastic":
            v = self._w[ks] * a[self._frame[ks]] * (1.0 - rng.random(ks.size))  # (1 - U) W_ID->FLC a ([BBc])
        else:  # "most_active" ("nearest" is :meth:`_nearest_target`)
            v = 0.5 + 0.5 * rng.random(ks.size)  # a random unvisited feature of the leading frame ([S])
        if visited:
            if active.size == 1:  # ks is the range f0, f0 + 1, ...: a visited feature k sits at k - f0
                hit = [k - f0 for k in visited if f0 <= k < f0 + ks.size]
            else:
                vis = set(visited)
                hit = [i for i, k in enumerate(ks.tolist()) if k in vis]
            v[hit] = 0.0
        return ks, v
