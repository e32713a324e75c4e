"""Map correction: when and how the cognitive map's node poses are solved (paper §2.4, Eq. 14).

The layer of :class:`~hippomap.cognitive_map.CognitiveMap` above its graph
(:class:`~hippomap.map_graph.MapGraph`) and the branches its whole solves start from
(:class:`~hippomap.heading_branches.HeadingBranches`): after any change of the graph the map is corrected with
``MapConfig.solver`` (the algorithms are in :mod:`hippomap.relaxation`): nothing is done while the
map agrees with itself; a local window or the whole map is solved otherwise; once converged, the
robust weights of the loop links are revised from their residuals (iteratively reweighted
relaxation, :func:`~hippomap.robust_kernel.kernel_weights`), which starts the correction again when
a weight changed. This layer also gives each link its information (the weighted solver's and the
g2o export's weights) and estimates the odometry's heading bias with the whole solves.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from .graph_paths import hop_distances
from .heading_branches import _FADED_INFORMATION, HeadingBranches
from .least_squares import bias_sigma, solve_lsq
from .map_events import MapEvent, MapRelaxed
from .map_graph import LOOP, ODOMETRY
from .relaxation import ColourGroups, RelaxResult, _link_residuals, relax, relax_jacobi
from .robust_kernel import USED_WEIGHT

__all__ = ["MapCorrection"]

_STALE_FACTOR = 10.0  # a loop link's weight falling by this factor is revised whatever reweight_tolerance says


class MapCorrection(HeadingBranches):
    """The map's correction and robust reweighting, over :class:`~hippomap.heading_branches.HeadingBranches`."""

    def _optimise(self, t: float, force: bool = False, sweeps: int | None = None) -> list[MapEvent]:
        """Correct node poses while the graph disagrees with itself (``MapConfig.solver``).

        Nothing is done while the map is consistent (every link added since the last
        correction agreed with the poses, as a new node's odometric link does): between loop
        closures the cost per step does not grow with the map. After a closure, 'relax' runs
        ``relax_loops`` sweeps per step until the largest shift of a sweep falls below
        ``relax_tolerance_m``; 'lsq' solves at once. Once converged, the loop links'
        robust weights are revised (:meth:`_reweight`); a change of weight starts it again.
        """
        m, n = self._m, self._n
        if m == 0 or not (self._dirty or force):
            return []
        P = self._P[:n]
        src, dst, tr = self._src[:m], self._dst[:m], self._tr[:m]
        cfg = self.cfg
        sweeps = cfg.relax_loops if sweeps is None else int(sweeps)
        w = self._w[:m]
        window = None
        if not force and self._deferred(t):
            return []
        self._solved_path, self._solved_t = self._path, t
        if cfg.solver == "lsq" and not force and not self._whole_due():
            window = self._local_window()
        # a whole solve of changes that all agree with the map: no headings-first init (see _solve_lsq)
        init = cfg.solver != "lsq" or force or window is not None or not self._small_change()
        self._touched = []  # what is solved now; the reweighting below may add to it
        if cfg.solver == "lsq":
            res, converged = self._solve_lsq(window, rotation_init=init)
        elif sweeps <= 0:
            return []
        elif cfg.solver == "jacobi":
            res = relax_jacobi(P, src, dst, tr, sweeps, cfg.alpha, anchor=0)
            converged = res.max_shift < cfg.relax_tolerance_m
        else:
            if self._groups_key != self._version:
                self._groups = ColourGroups(src, dst, tr, self._col[:m], n, check=False, weights=w)
                self._groups_key = self._version
            res = relax(P, src, dst, tr, sweeps, cfg.alpha, anchor=0, groups=self._groups)
            converged = res.max_shift < cfg.relax_tolerance_m
        # robust weights are revised on a map solved whole only: a window holds the rest of the map
        # fixed, and the strain at its edge would fade true links
        self._dirty = not converged or (self._local_solves == 0 and self._reweight())
        return [MapRelaxed(res.solver, res.iterations, res.max_shift, t)]

    def _whole_due(self) -> bool:
        """Whether the next correction solves the whole map (and revises the robust weights): after
        ``lsq_window_every`` local solves, once those have moved, summed, ``lsq_whole_every_map`` times the
        map's nodes (docs/MODEL.md item 108), and have done, summed, ``lsq_whole_every_work`` times the last whole
        solve's work (its factors' nonzeros, :attr:`~hippomap.relaxation.RelaxResult.work`; item 117). A whole solve's
        cost grows with the map and a local one's with its window: counted in local solves alone, the whole solves'
        share of a step grew with the map's size; counted in nodes, it still grew with the laps of a path retraced
        again and again, whose loop links make each node's share of the factor grow."""
        cfg = self.cfg
        if self._local_solves < cfg.lsq_window_every:
            return False
        k, kw = cfg.lsq_whole_every_map, cfg.lsq_whole_every_work
        if kw is not None and self._local_work < kw * self._whole_work:
            return False
        return k is None or self._local_moved >= k * self._n

    def _deferred(self, t: float) -> bool:
        """Whether the correction at time ``t`` waits (``lsq_defer_m``, ``lsq_defer_s``): the 'lsq'
        solver has solved within the last ``lsq_defer_m`` of path and ``lsq_defer_s`` seconds, and
        every link changed since agrees with the map within ``lsq_window_residual_m``
        (:meth:`_small_change`). On a revisit every key frame closes another small loop; solving the
        map for each made the solves a third of the mapper's cost, while the changes they carry are
        each a few centimetres. They are kept and solved together once the robot has gone
        ``lsq_defer_m`` further or ``lsq_defer_s`` has passed (a robot that stops or turns on the
        spot still gets its map settled), or at once when a change that disagrees with the map
        arrives: a new loop is never kept waiting."""
        cfg = self.cfg
        return (
            cfg.solver == "lsq"
            and cfg.lsq_defer_m > 0
            and self._path - self._solved_path < cfg.lsq_defer_m
            and t - self._solved_t < cfg.lsq_defer_s
            and self._small_change()
        )

    def _solve_lsq(
        self, window: tuple[np.ndarray, np.ndarray, np.ndarray] | None, rotation_init: bool = True
    ) -> tuple[RelaxResult, bool]:
        """The 'lsq' solve of :meth:`_optimise`: the whole map (headings first when
        ``lsq_rotation_init`` and ``rotation_init``; the odometry's bias estimated with the poses), or
        only the nodes of ``window`` (:meth:`_local_window`) with the nodes just outside it fixed.
        Returns the solver's result and whether it converged.

        ``rotation_init`` False: every changed link agrees with the map within
        ``lsq_window_residual_m`` (:meth:`_small_change`), so no heading error is left to spread
        and the headings-first init is skipped: its cost test almost never kept it in such solves
        (docs/MODEL.md)."""
        m, n = self._m, self._n
        P = self._P[:n]
        src, dst, tr = self._src[:m], self._dst[:m], self._tr[:m]
        cfg = self.cfg
        w = self._w[:m]
        info = (self.link_information() if cfg.lsq_weighted else np.ones((m, 3))) * w[:, None]
        bias = self._bias_args()
        if window is None:
            res = self._whole_solve(P, src, dst, tr, info, bias, rotation_init=cfg.lsq_rotation_init and rotation_init)
            self._local_solves = self._local_moved = self._local_work = 0
            self._whole_work = res.work
        else:
            self._local_solves += 1
            nodes, links, fixed = window
            self._local_moved += len(nodes) - len(fixed)
            local = np.full(n, -1, dtype=np.int64)
            local[nodes] = np.arange(len(nodes))
            Q = P[nodes].copy()
            if bias:
                bias = {**bias, "bias_dt": bias["bias_dt"][links], "estimate_bias": False}
            res = solve_lsq(
                Q,
                local[src[links]],
                local[dst[links]],
                tr[links],
                iterations=cfg.lsq_window_iterations or cfg.lsq_iterations,
                tol=cfg.lsq_step_tolerance,
                anchor=None,
                information=info[links],
                fixed=local[fixed],
                coupling=self._lcoup[links],
                **bias,
            )
            P[nodes] = Q
            self._local_work += res.work
        # a solve cut off by lsq_iterations has not converged: the weights are revised only on a
        # converged map (IRLS), else a closure still being applied looks like an outlier and fades
        converged = res.iterations < cfg.lsq_iterations or res.max_shift < cfg.relax_tolerance_m
        return res, converged

    def _whole_solve(
        self,
        P: np.ndarray,
        src: np.ndarray,
        dst: np.ndarray,
        tr: np.ndarray,
        info: np.ndarray,
        bias: dict[str, Any],
        rotation_init: bool,
    ) -> RelaxResult:
        """A whole-map 'lsq' solve of ``P`` in place (headings first when ``rotation_init``).

        With the bias estimated (``bias`` not empty), the poses and the bias are solved together on
        a copy, and the result is kept only when the bias is significant: ``|b| >
        odometry_bias_significance × σ_b``, σ_b its posterior standard deviation at the solution
        (:func:`~hippomap.least_squares.bias_sigma`, a Wald test), and observed by the loops: ``σ_b ≤
        odometry_bias_observed × odometry_bias_sigma`` (the closures, not the prior, carry it). Otherwise
        the bias is taken as 0 and the map is solved without it, exactly as with the option off: a bias
        that the loops cannot tell from the odometry's own noise is not applied, so that loop links'
        errors cannot pose as one. A solve that starts from a turned heading branch weighs each loop link
        as the kernel does on the branch, not as on the map before it (docs/MODEL.md item 77)."""
        cfg = self.cfg
        solve: dict[str, Any] = {
            "iterations": cfg.lsq_iterations,
            "tol": cfg.lsq_step_tolerance,
            "anchor": 0,
            "information": info,
            "coupling": self._lcoup[: self._m],  # the map's links: a whole solve's are all of them
        }
        work = 0  # a solve with the bias whose estimate is not kept is work done all the same
        if bias:
            Q = P.copy()
            b, at = self._rotation_init(Q, src, dst, tr, info, bias) if rotation_init else (self._bias, info)
            res = solve_lsq(Q, src, dst, tr, **{**solve, "information": at}, **{**bias, "bias": b})
            sd, kept = self._bias_kept(Q, src, dst, tr, at, bias, res.bias)
            if kept:
                P[:] = Q
                self._bias, self._bias_sd, self._bias_unkept = res.bias, sd, 0.0
                return res
            self._bias = 0.0
            # the gate allows for the estimate all the same (loop_bias_unkept, docs/MODEL.md item 125)
            self._bias_sd, self._bias_unkept = (sd, abs(res.bias)) if cfg.loop_bias_unkept else (0.0, 0.0)
            work = res.work
        if rotation_init:
            solve["information"] = self._rotation_init(P, src, dst, tr, info, {})[1]
        res = solve_lsq(P, src, dst, tr, **solve)
        return replace(res, work=res.work + work)

    def _bias_kept(
        self,
        Q: np.ndarray,
        src: np.ndarray,
        dst: np.ndarray,
        tr: np.ndarray,
        info: np.ndarray,
        bias: dict[str, Any],
        b: float,
    ) -> tuple[float, bool]:
        """(σ_b, whether the estimate ``b`` of the solution ``Q`` is kept). Kept: significant (``|b| >
        odometry_bias_significance × σ_b``, σ_b its posterior standard deviation there, a Wald test)
        and observed by the loops (``σ_b ≤ odometry_bias_observed × odometry_bias_sigma``), σ_b counting
        only the loop links whose heading ``Q`` explains (:meth:`_used_information`). The gate widens
        with σ_b (:meth:`_bias_drift`), and with ``|b|`` too when it is not kept (``map.loop_bias_unkept``)."""
        cfg = self.cfg
        k, bound = cfg.odometry_bias_significance, cfg.odometry_bias_observed
        used = self._used_information(info, Q)
        sigma = bias_sigma(Q, src, dst, tr, bias["bias_dt"], b, bias["bias_information"], used)
        if k <= 0 and bound is None:  # no test: any estimate off zero is kept
            return sigma, abs(b) > 0
        observed = bound is None or sigma <= bound * cfg.odometry_bias_sigma
        return sigma, bool(abs(b) > k * sigma and observed)

    def _used_information(self, info: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """``info`` (M, 3) without the loop links whose heading the solved poses ``Q`` leave
        inconsistent: what observes the odometry's bias in its significance test. The bias is a
        heading rate, so a loop link is evidence for an estimate only when its heading residual on
        the solution is within its kernel width (the heading part of its robust weight at least
        ``USED_WEIGHT``); a false closure the estimate cannot explain is not."""
        cfg = self.cfg
        loop = self._loop_ids()
        if not len(loop) or cfg.loop_kernel == "none":
            return info
        faded = loop[self._loop_weights(Q, loop, heading_only=True) < USED_WEIGHT]
        if not len(faded):
            return info
        out = info.copy()
        out[faded] *= _FADED_INFORMATION  # (the solver's information must stay > 0)
        return out

    def _bias_args(self) -> dict[str, Any]:
        """Keyword arguments of :func:`solve_lsq` for the odometry's heading bias (empty when
        ``odometry_bias_sigma`` is 0): every odometric link's heading change is taken to include
        ``bias × its duration`` (a gyro's or wheel odometry's constant turn rate error), and the
        whole solves estimate the bias with the poses, from a zero-mean prior of that sigma, and
        keep it only when it is significant (:meth:`_whole_solve`)."""
        sigma = self.cfg.odometry_bias_sigma
        if sigma <= 0:
            return {}
        m = self._m
        bdt = np.where(self._kind[:m] == ODOMETRY, self._dt[:m], 0.0)
        return {"bias_dt": bdt, "bias": self._bias, "bias_information": 1.0 / sigma**2}

    def _reweight(self) -> bool:
        """Revise the robust weights of the loop links from their residuals on the converged
        map (iteratively reweighted relaxation): each link's residual is whitened by
        ``loop_information`` and the kernel width, and ``loop_kernel`` turns it into a weight in
        (0, 1]. Returns whether a weight changed by more than ``reweight_tolerance`` or fell tenfold."""
        cfg = self.cfg
        if cfg.loop_kernel == "none":
            return False
        loop = self._loop_ids()
        if not len(loop):
            return False
        new = self._loop_weights(self._P[: self._n], loop)
        old = self._w[loop]
        # a faded link's weight falling tenfold is a change too, however small in absolute terms: its
        # stale weight times a residual of tens of metres would go on bending the map (docs/MODEL.md item 52)
        changed = (np.abs(new - old) > cfg.reweight_tolerance) | (old > _STALE_FACTOR * new)
        if not changed.any():
            return False
        self._w[loop] = new
        self._touched.extend(loop[changed].tolist())
        self._version += 1  # rebuild the relaxation groups with the new gains
        return True

    def _local_window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(nodes, links, fixed) of a local solve, or None for a solve of the whole map.

        When every link changed since the last solve disagrees with the map by less than
        ``lsq_window_residual_m``, the correction is local (the robot is re-localising along a
        mapped path, not closing a new loop): only the nodes within ``lsq_window_hops`` links of
        their ends move, the nodes just outside hold the rest of the map in place. The cost of
        such a step then depends on the window, not on the map (:meth:`finish` solves the
        whole map). A window that moves more than ``lsq_window_max_fraction`` of the nodes, or
        has no node outside it to hold, is the whole map's solve."""
        cfg, n, m = self.cfg, self._n, self._m
        if cfg.lsq_window_hops <= 0 or not self._small_change():
            return None
        k = np.unique(np.asarray(self._touched, dtype=np.int64))
        k = k[k < m]
        src, dst = self._src[:m], self._dst[:m]
        d = hop_distances(n, src, dst, np.concatenate([src[k], dst[k]]), cfg.lsq_window_hops)
        active = d <= self._window_hops(d)
        active[0] = False  # the anchor never moves
        links = np.flatnonzero(active[src] | active[dst])
        if not len(links) or active.sum() > cfg.lsq_window_max_fraction * n:
            return None  # the window is most of the map: solve it all
        nodes = np.unique(np.concatenate([src[links], dst[links]]))
        fixed = nodes[~active[nodes]]
        if not len(fixed):
            return None
        return nodes, links, fixed

    def _window_hops(self, d: np.ndarray) -> int:
        """The hops of a local solve's window, given each node's hop distance ``d`` from the changed links
        (``inf`` beyond ``lsq_window_hops``): ``lsq_window_hops``, or the most hops whose window holds at
        most ``lsq_window_max_nodes`` nodes. On a path retraced many times the window reaches every pass
        through the loop links, so with hops alone its size, and a step's cost, grows with the laps."""
        cfg = self.cfg
        cap = cfg.lsq_window_max_nodes
        if cap is None:
            return cfg.lsq_window_hops
        within = np.cumsum(np.bincount(d[np.isfinite(d)].astype(np.int64), minlength=cfg.lsq_window_hops + 1))
        fits = np.flatnonzero(within <= cap)
        return int(fits[-1]) if len(fits) else 0

    def _small_change(self) -> bool:
        """Every link added or changed since the last solve agrees with the map within
        ``lsq_window_residual_m``, or within ``lsq_window_anchored_residual_m`` when the links beyond the narrower
        bar are visual (:meth:`_loosened`) and the map round the robot is anchored (:meth:`_anchored`); False when
        there is none, or the whole map changed."""
        touched, m = self._touched, self._m
        if not touched or -1 in touched:
            return False
        k = np.unique(np.asarray(touched, dtype=np.int64))
        k = k[k < m]
        if not len(k):
            return False
        r = _link_residuals(self._P[: self._n], self._src[k], self._dst[k], self._tr[k])
        res, cfg = np.hypot(r[:, 0], r[:, 1]), self.cfg
        worst, wide = float(res.max()), cfg.lsq_window_anchored_residual_m
        if worst <= cfg.lsq_window_residual_m:
            return True
        if wide is None or worst > wide:
            return False
        return self._loosened(k[res > cfg.lsq_window_residual_m]) and self._anchored(k)

    def _loosened(self, links: np.ndarray) -> bool:
        """Whether ``links`` are all loop links the solve holds looser along their x than the kernel judges them
        (``_linfo`` below ``_lkpos``: a visual link, with looming's ``along_sigma`` and ``visual_solve_loosening``).
        Such a link's disagreement of a few decimetres is mostly its own error (a depth misread); a measured
        transform's is the map's, and a local solve that holds the rest of the map would squeeze it into the window."""
        return bool(np.all(self._kind[links] == LOOP) and np.all(self._linfo[links, 0] < self._lkpos[links]))

    def _anchored(self, changed: np.ndarray) -> bool:
        """Whether a used loop link (robust weight >= ``USED_WEIGHT``) that is not among the ``changed`` ones
        lies within ``lsq_window_hops`` links of the robot's end of a changed link (the end made later): the
        robot is re-localising on a map a closure already holds there, not closing a new loop, whose first
        link after a long drift can agree with the drifted map by coincidence and must be solved whole."""
        m = self._m
        src, dst = self._src[:m], self._dst[:m]
        loop = self._loop_ids()  # a retracted link (kernel width 0) sits at the floor weight: never used
        used = np.setdiff1d(loop[self._w[loop] >= USED_WEIGHT], changed)
        if not len(used):
            return False
        S = self._S
        robot = np.where(S[src[changed]] >= S[dst[changed]], src[changed], dst[changed])
        d = hop_distances(self._n, src, dst, robot, self.cfg.lsq_window_hops)
        return bool(np.isfinite(d[src[used]]).any() or np.isfinite(d[dst[used]]).any())

    def link_information(self) -> np.ndarray:
        """(M, 3) diagonal information of every link (x, y, θ) for the weighted solver: odometric
        and prune links ``odometry_information_per_m / length`` (variance grows with the path;
        lengths below 5 cm count as 5 cm), the heading's variance also ``odometry_turn_variance``
        per radian turned; loop links their own (``loop_information``, ``visual_loop_information`` with
        ``visual_lateral_information``, x loosened by a looming offset's ``along_sigma``, a visual link's x and y
        divided by ``visual_solve_loosening``)."""
        m = self._m
        cfg = self.cfg
        length = np.maximum(np.hypot(self._tr[:m, 0], self._tr[:m, 1]), 0.05)
        xy, th = cfg.odometry_information_per_m
        turn = np.abs(self._tr[:m, 2])
        info = np.column_stack([xy / length, xy / length, 1.0 / (length / th + cfg.odometry_turn_variance * turn)])
        loop = self._kind[:m] == LOOP
        info[loop] = self._linfo[:m][loop]
        return info

    def link_coupling(self) -> np.ndarray:
        """(M,) each link's heading-lateral coupling (m⁻¹; 0 but on coupled visual loop links,
        :attr:`~hippomap.loop_closure.LoopHypothesis.coupling`): with :meth:`weighted_link_information`,
        the link's full information matrix, which the g2o export writes."""
        return self._lcoup[: self._m].copy()

    def weighted_link_information(self) -> np.ndarray:
        """(M, 3) diagonal information (x, y, θ) the map gives each link when it solves: the
        solver's weights (:meth:`link_information`; unit information when ``lsq_weighted`` is
        off) times each link's robust weight (a faded loop link counts for little). This is what
        the g2o export writes on each edge."""
        info = self.link_information() if self.cfg.lsq_weighted else np.ones((self._m, 3))
        return info * self._w[: self._m, None]

    def finish(self, iterations: int | None = None) -> list[MapEvent]:
        """End of a run: one more correction (``iterations`` sweeps, default ``relax_loops``; an
        exact solve for 'lsq') and the queued events. Pending hypotheses stay pending."""
        events, self._events = self._events, []
        events.extend(self._optimise(self._t if self._t is not None else 0.0, force=True, sweeps=iterations))
        return events
