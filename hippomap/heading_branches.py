"""Heading branches: which reading of the loop links' heading residuals a whole solve starts from (paper
§2.4, Eq. 14; docs/MODEL.md items 53, 54, 74–76).

A loop link's heading residual is known only up to whole turns: a closure alone cannot tell a drift of
+3.4 rad from one of −2.9 rad, nor three turns of drift from none. Before a whole solve the map's
headings are re-initialised headings first (:func:`~hippomap.headings_first.rotation_first_inits`) from
the wrapped reading and from branches that take the loop links the map does not use whole turns further
round; a turned branch is kept when it explains the map clearly better at an ordinary drift rate, or at a
faster one when it adds little cost to the map; a turned branch that starts below the wrapped reading is judged,
with it, after a short solve (item 112). This layer, below
:class:`~hippomap.map_correction.MapCorrection`, holds these tests and the robust weights loop links
would have on given poses.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache, partial
from typing import Any

import numpy as np

from .headings_first import rate_turns, rotation_first_inits, turn_rates
from .least_squares import graph_cost, solve_lsq
from .loop_closure import link_errors
from .map_graph import LOOP, MapGraph
from .relaxation import _wrap_inplace
from .robust_kernel import USED_WEIGHT

__all__ = ["HeadingBranches"]

_FADED_INFORMATION = 1e-12  # what is left of a faded loop link's information where a cost must leave it out
_BRANCH_TURNS = (-2, -1, 1, 2)  # whole turns the headings-first init always tries on loop links the map does not use
_BRANCH_MARGIN = 0.5  # ... and keeps only at under this fraction of the wrapped reading's cost, at a rate within
# odometry_bias_sigma (docs/MODEL.md item 53)
_BRANCH_WIDE = 3.0  # ... or within this many odometry_bias_sigma when the branch fits every link well (item 54)
_BRANCH_FIT_P = 0.99  # ... "well": the cost it adds within this chi-square quantile, 3 dof per turned link
_BRANCH_MAX_TURNS = 8  # further turns tried, up to this many, for a link that reads so as a rate within _BRANCH_WIDE
# sigmas (docs/MODEL.md item 76)
_RATE_BRANCHES = 4  # branches with turns chosen link by link for one drift rate (_rate_branches), the best supported
_RATE_AGREE_RAD = 0.5  # ... a rate explains a link when its turned residual is within this of what the rate asks


def _short_solve(
    Q: np.ndarray, b: float, steps: int, graph: tuple[np.ndarray, ...], bias: dict[str, Any]
) -> tuple[np.ndarray, float, float]:
    """A branch's init ``Q`` (with bias ``b``) after ``steps`` Gauss-Newton steps of the whole solve on ``graph``
    (sources, targets, transforms, information, coupling), on a copy: (its poses, its bias, its cost)."""
    src, dst, tr, info, coupling = graph
    P = Q.copy()
    res = solve_lsq(P, src, dst, tr, iterations=steps, information=info, coupling=coupling, **{**bias, "bias": b})
    b = float(res.bias) if bias else b
    return P, b, graph_cost(P, src, dst, tr, info, coupling=coupling, **{**bias, "bias": b})


class HeadingBranches(MapGraph):
    """The headings-first re-initialisation's branches of a whole solve, over :class:`~hippomap.map_graph.MapGraph`."""

    def _loop_ids(self) -> np.ndarray:
        """The indices of the map's loop links (the links its robust kernel weighs)."""
        return np.flatnonzero((self._kind[: self._m] == LOOP) & (self._lkw[: self._m] > 0))

    def _map_cost(self, Q: np.ndarray, info: np.ndarray, bias: dict[str, Any]) -> float:
        """The whole solve's cost (:func:`~hippomap.least_squares.graph_cost`) of every link of the map on
        the poses ``Q`` with the information ``info`` (M, 3), the map's coupled heading residuals included."""
        m = self._m
        return graph_cost(Q, self._src[:m], self._dst[:m], self._tr[:m], info, coupling=self._lcoup[:m], **bias)

    def _loop_weights(self, P: np.ndarray, loop: np.ndarray, heading_only: bool = False) -> np.ndarray:
        """The ``loop_kernel`` weights the loop links ``loop`` would have on the poses ``P``: each link's
        residual in its source frame, coupled (:func:`~hippomap.loop_closure.link_errors`), weighed by
        :meth:`_kernel_weights`; with ``heading_only`` the heading part alone (x/y residuals taken as 0,
        no coupling)."""
        src, dst, tr = self._src[loop], self._dst[loop], self._tr[loop]
        if heading_only:
            r = link_errors(P, src, dst, tr)
            r[:, :2] = 0.0
        else:
            r = link_errors(P, src, dst, tr, self._lcoup[loop])
        return self._kernel_weights(r, loop)

    def _rotation_init(
        self, P: np.ndarray, src: np.ndarray, dst: np.ndarray, tr: np.ndarray, info: np.ndarray, bias: dict[str, Any]
    ) -> tuple[float, np.ndarray]:
        """Headings-first re-initialisation before a whole solve (with the bias when it is
        estimated), kept only when it lowers the weighted cost (it cannot on a map that is
        already at its optimum); with loop links the map does not use, from each branch of
        :meth:`_heading_branches` too, a turned branch kept only at under ``_BRANCH_MARGIN`` of the
        cost and at a rate within ``odometry_bias_sigma`` (a lone false closure can be explained by a
        whole extra turn at an extraordinary rate), or within ``_BRANCH_WIDE`` of it when the branch
        fits every link (:meth:`_branch_rate_ok`). Costs are the whole solve's own, the map's coupled
        heading residuals included. Returns the bias to start the solve from and the information to solve
        with: ``info``, or after a turned branch ``info`` with every loop link at the robust weight the kernel
        gives it on the branch (:meth:`_reweighted`; docs/MODEL.md item 77). When a turned branch starts below the
        wrapped reading, both are judged after ``lsq_branch_solve_iterations`` steps of the solve (item 112)."""
        b0 = float(bias.get("bias", 0.0))
        coupling = self._lcoup[: self._m]
        best_cost, best = graph_cost(P, src, dst, tr, info, coupling=coupling, **bias), None
        branches = self._heading_branches(P)
        inits = rotation_first_inits(P, src, dst, tr, info, anchor=0, branches=branches, **bias)
        base = cache(partial(self._odometry_share, P, info, bias))
        costs = [graph_cost(Q, src, dst, tr, info, coupling=coupling, **{**bias, "bias": b}) for Q, _, b in inits]
        # a turned branch that starts below the wrapped reading (branches[0]) is judged, with it, where a short solve
        # takes it: an init's cost can favour a branch a few steps of the solve leave behind (docs/MODEL.md item 112)
        steps = self._branch_solve_steps()
        refine = steps is not None and any(t is not None and c < costs[0] for t, c in zip(branches, costs))
        for turns, (Q, _, b), cost in zip(branches, inits, costs):
            if refine and (turns is None or cost < costs[0]):
                Q, b, cost = _short_solve(Q, b, int(steps or 0), (src, dst, tr, info, coupling), bias)
            at_b = {**bias, "bias": b}
            # another branch must explain the map clearly better than the wrapped reading, at an ordinary rate
            if turns is None:
                better = cost < best_cost
            else:
                fit = partial(self._branch_fit, Q, info, at_b, turns, base)
                better = cost < _BRANCH_MARGIN * best_cost and self._branch_rate_ok(b, fit)
            if better:
                best_cost, best = cost, (Q, b, turns)
        if best is None:
            return b0, info
        Q, b, turns = best
        P[:] = Q
        return b, info if turns is None else self._reweighted(Q, info)

    def _branch_solve_steps(self) -> int | None:
        """Gauss-Newton steps a turned branch that starts below the wrapped reading is judged after
        (``lsq_branch_solve_iterations``; None: judged at its init)."""
        return self.cfg.lsq_branch_solve_iterations

    def _branch_rate_ok(self, b: float, fit: Callable[[], tuple[float, int]]) -> bool:
        """Whether a turned branch's rate ``b`` may be taken: within ``odometry_bias_sigma``, or within
        ``_BRANCH_WIDE`` sigmas when the branch fits: ``fit()`` (:meth:`_branch_fit`) gives the cost it
        adds to the map within the chi-square ``_BRANCH_FIT_P`` quantile of its degrees of freedom. A gyro
        drifting faster than sigma is then unwound when the turn makes the links agree; a lone false
        closure that one extra turn half explains bends the odometry between its ends and stays far above
        (docs/MODEL.md items 54, 75 and 76)."""
        sigma = self.cfg.odometry_bias_sigma
        if abs(b) <= sigma:
            return True
        if abs(b) > _BRANCH_WIDE * sigma:
            return False
        from scipy.special import chdtri  # the chi-square quantile; needed only here, rarely

        cost, dof = fit()
        return bool(cost <= chdtri(dof, 1.0 - _BRANCH_FIT_P))

    def _branch_fit(
        self, Q: np.ndarray, info: np.ndarray, bias: dict[str, Any], turns: np.ndarray, base: Callable[[], float]
    ) -> tuple[float, int]:
        """What a turned branch's init ``Q`` is judged by in the fit test of :meth:`_branch_rate_ok`: the
        cost the branch adds to the map, 3 degrees of freedom per turned link. Its cost is the whole
        solve's with every loop link at the robust weight the kernel gives it on ``Q`` (one reweighting
        step): the map's weights were given on another map, and a closure faded as false there keeps its
        small weight while the branch moves its residual by metres (docs/MODEL.md item 75). From it is
        taken ``base()``, the cost the map already had without the links it does not use
        (:meth:`_odometry_share`): its odometry, bent to half fit closures the wrapped reading cannot
        explain, and the closures it uses are costs the branch does not add, which a bound of 3 degrees of
        freedom per turned link cannot hold (item 76)."""
        return self._map_cost(Q, self._reweighted(Q, info), bias) - base(), 3 * int(np.count_nonzero(turns))

    def _reweighted(self, Q: np.ndarray, info: np.ndarray) -> np.ndarray:
        """``info`` (M, 3) with every loop link at the robust weight the kernel gives it on the poses ``Q``
        instead of the map's (one step of the iteratively reweighted solve, started on ``Q``)."""
        loop = self._loop_ids()
        out = info.copy()
        out[loop] *= (self._loop_weights(Q, loop) / self._w[loop])[:, None]
        return out

    def _odometry_share(self, P: np.ndarray, info: np.ndarray, bias: dict[str, Any]) -> float:
        """The whole solve's cost on the map ``P`` without the loop links ``P`` does not use (robust weight
        below ``USED_WEIGHT``): what the map's odometry and its agreeing closures already cost before a
        branch turns the others (:meth:`_branch_fit`)."""
        kept = info.copy()
        kept[self._unused_loops(P)] *= _FADED_INFORMATION  # (information must stay > 0)
        return self._map_cost(P, kept, bias)

    def _unused_loops(self, P: np.ndarray) -> np.ndarray:
        """The loop links the poses ``P`` do not use (robust weight on ``P`` below ``USED_WEIGHT``: new
        closures, faded ones): those a branch turns, and those the map's own share leaves out."""
        loop = self._loop_ids()
        return loop[self._loop_weights(P, loop) < USED_WEIGHT]

    def _heading_branches(self, P: np.ndarray) -> list[np.ndarray | None]:
        """The branches of the loop links' heading residuals the headings-first init tries: each
        wrapped into (−π, π] as it reads on ``P`` (None), then the loop links ``P`` does not use
        (robust weight on ``P`` below ``USED_WEIGHT``: new closures, faded ones) taken together
        whole turns further round (each (M,), :meth:`_branch_turns`). A closure alone cannot tell a
        drift of +3.4 rad from one of −2.9 rad, nor of +6.1 rad from −0.2 rad; the positions the
        branches give can (docs/MODEL.md item 53); then the branches one drift rate gives, whose turns
        differ from link to link (:meth:`_rate_branches`, item 74)."""
        if self.cfg.loop_kernel == "none":
            return [None]
        unused = self._unused_loops(P)
        if not len(unused):
            return [None]
        src, dst = self._src[unused], self._dst[unused]
        residual = _wrap_inplace(P[dst, 2] - P[src, 2] - self._tr[unused, 2])  # as the headings solve reads them
        duration = self._Tn[dst] - self._Tn[src]
        whole = self._branch_turns(residual, duration)
        uniform = [self._on_links(unused, k) for k in whole]
        return [None, *uniform, *self._rate_branches(unused, residual, duration, whole, uniform)]

    def _branch_turns(self, residual: np.ndarray, duration: np.ndarray) -> tuple[int, ...]:
        """The whole turns the branches take the unused loop links round: ``_BRANCH_TURNS`` always, and
        further ones, up to ``_BRANCH_MAX_TURNS``, that some link's turned residual over its duration
        (``residual`` and ``duration`` (U,), s) reads as a rate within ``_BRANCH_WIDE`` sigmas, the most
        :meth:`_branch_rate_ok` ever takes. A gyro drifting 0.03 rad/s turns the headings 18.7 rad, three
        whole turns, in the 622 s between a place and its first revisit on a long route, and the branch that
        unwinds it is never tried with two (docs/MODEL.md item 76)."""
        sigma = self.cfg.odometry_bias_sigma
        far = np.arange(max(_BRANCH_TURNS) + 1, _BRANCH_MAX_TURNS + 1, dtype=float)
        if sigma <= 0 or not far.size:
            return _BRANCH_TURNS
        far = np.concatenate([-far[::-1], far])
        reach = np.any(np.abs(self._bias + turn_rates(residual, duration, far)) <= _BRANCH_WIDE * sigma, axis=0)
        return tuple(sorted({*_BRANCH_TURNS, *far[reach].astype(int).tolist()}))

    def _rate_branches(
        self,
        unused: np.ndarray,
        residual: np.ndarray,
        duration: np.ndarray,
        whole: tuple[int, ...],
        uniform: list[np.ndarray],
    ) -> list[np.ndarray]:
        """Branches whose turns differ from link to link (:func:`~hippomap.headings_first.rate_turns`): the
        turns (``whole`` of them at most) one drift rate, within ``_BRANCH_WIDE`` sigmas, asks of each
        unused loop link from its wrapped heading ``residual`` and its ``duration`` (the times of its
        nodes); up to ``_RATE_BRANCHES`` that are not among the ``uniform`` ones (docs/MODEL.md item 74)."""
        sigma = self.cfg.odometry_bias_sigma
        if sigma <= 0 or len(unused) < 2:
            return []
        branches = rate_turns(
            residual,
            duration,
            self._bias,
            _BRANCH_WIDE * sigma,
            turns=whole,
            limit=_RATE_BRANCHES,
            agree_rad=_RATE_AGREE_RAD,
            exclude=[t[unused] for t in uniform],
        )
        return [self._on_links(unused, k) for k in branches]

    def _on_links(self, links: np.ndarray, turns: float | np.ndarray) -> np.ndarray:
        """A branch's turns over the map's links (M,): ``turns`` on ``links`` (one number for all, or one
        each), none on the others."""
        out = np.zeros(self._m)
        out[links] = turns
        return out
