"""The visual memory's fast paths give exactly what the straightforward computation gives.

:class:`ReferenceMemory` keeps, in this file, the plain implementation of every part the fast code
replaces: the FLC drive as one ``np.take`` over freshly gathered patches for every fixation (summed
along each row by ``einsum``, as the fast code defines the drive), the
saccade vector decoded from the two grid codes every time, the retina run on every call, no drive
remembered per fixation point, ``dataclasses.asdict`` for a trace step, the candidate subset built
from ``np.unique`` with nothing shared between recognitions, and the fixation bookkeeping (trace
step, leading frames, survivors, frame activity, next target) as first written. Recognitions
(winning frame, evidence, every step of the saccade trace, correspondences) and the learned state
must be identical, bit for bit, for the exact path, the index path, candidate subsets, a decoder
variant and rejected queries.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, cast

import numpy as np
import pytest

from hippomap import feature_store
from hippomap import visual_memory as vm
from hippomap.config import VisualConfig
from hippomap.errors import InputError
from hippomap.retina import imadjust
from hippomap.sim.scenes import shapes_scene
from hippomap.visual_grid_cells import VisualGridCells


def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def reference_decode_phase_difference(grid: VisualGridCells, delta: np.ndarray) -> np.ndarray:
    """VisualGridCells.decode_phase_difference as written for any batch shape (the fast code has a
    path of its own for one pair)."""
    self = grid
    delta = np.asarray(delta, dtype=float)
    c = self._order[0]
    z = _wrap(delta[..., c, :])
    z2 = z[..., 1] - z[..., 0] + _wrap(z[..., 2] - (z[..., 1] - z[..., 0]))
    z = np.stack([z[..., 0], z[..., 1], z2], axis=-1)
    d0 = (2.0 / 3.0) * (z @ self.b) / self.F[c]
    alt = d0[..., None, :] + self._lattice_shifts
    co = self._coarse
    proj = alt @ self.b.T
    cost = (1.0 - np.cos(self.F[co, None] * proj[..., :, None, :] - delta[..., None, co, :])).sum(axis=(-1, -2))
    best = np.argmin(cost, axis=-1)
    d = np.take_along_axis(alt, best[..., None, None], axis=-2)[..., 0, :]
    for mods, wsum in ((co, self._w_coarse), (slice(None), self._w_all)):
        pred = self.F[mods, None] * (d @ self.b.T)[..., None, :]
        r = _wrap(delta[..., mods, :] - pred)
        d = d + ((self.F[mods, None] * r).sum(axis=-2) @ self.b) / wsum
    d0 = np.rint(d)
    cand = d0[..., None, :] + self._polish
    proj = cand @ self.b.T
    cost = (1.0 - np.cos(self.F[:, None] * proj[..., :, None, :] - delta[..., None, :, :])).sum(axis=(-1, -2))
    best = np.argmin(cost, axis=-1)
    return np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :].astype(np.int64)


class ReferenceSubset:
    """:class:`~hippomap.feature_store.FlcSubset` as first written: every array gathered for the subset
    alone, the statistics sample recomputed, the units' rows de-duplicated by ``np.unique``."""

    def __init__(self, mem, frames):
        n = mem.n_features
        if frames is None:
            self.idx = np.arange(n, dtype=np.int64)
            self.desc = mem._desc[:n]
        else:
            self.idx = (
                np.concatenate([np.arange(mem._fstart[f], mem._fstart[f] + mem._fcount[f]) for f in frames])
                if len(frames)
                else np.zeros(0, np.int64)
            ).astype(np.int64)
            self.desc = mem._desc[self.idx]
        self.n = int(self.idx.size)
        self.is_all = frames is None
        cfg = mem.config
        self.exact_all = self.n <= cfg.index_shortlist + cfg.stats_sample
        n_all = mem.n_features
        if self.is_all:
            self.sample = (
                None
                if self.exact_all
                else np.unique(np.linspace(0, self.n - 1, cfg.stats_sample).round().astype(np.int64))
            )
        else:
            self.sample = (
                np.arange(n_all, dtype=np.int64)
                if n_all <= cfg.index_shortlist + cfg.stats_sample
                else np.unique(np.linspace(0, n_all - 1, cfg.stats_sample).round().astype(np.int64))
            )
        small = n_all <= cfg.index_shortlist + cfg.stats_sample
        # the sample is driven apart over the statistics pixels unless it is every unit of a small library
        self.stats_apart = self.sample is not None and not small
        self.rows = None
        self.index_buf = None
        self.drives = {}
        self.all_local = np.arange(self.n)
        if self.exact_all:
            self.rows = self.idx if self.is_all or self.stats_apart else np.concatenate([self.idx, self.sample])
            uniq, inv = np.unique(self.rows, return_inverse=True)
            self.rows_inv = inv if uniq.size < self.rows.size else None
            gathered = uniq if self.rows_inv is not None else self.rows
            self.rows_hi = mem._patch[gathered].astype(np.uint16) << 8
            self.rows_z = mem._z[gathered]

    def local(self, global_index: int) -> int:
        if self.is_all:
            return int(global_index)
        i = int(np.searchsorted(self.idx, global_index))
        return i if i < self.n and int(self.idx[i]) == int(global_index) else -1


def reference_leading(a: np.ndarray, k: int) -> list[tuple[int, float]]:
    nz = np.flatnonzero(a > 0)
    if nz.size == 0:
        return []
    top = nz[np.argsort(-a[nz], kind="stable")[:k]]
    return [(int(f), float(a[f])) for f in top]


def _to_img(p, scale):
    return None if p is None else (float(p[0]) * scale, float(p[1]) * scale)


class ReferenceMemory(vm.VisualMemory):
    """The memory with its fast paths replaced by the plain computation they must equal."""

    def _drive(self, patch: np.ndarray, flc: np.ndarray, out=None) -> np.ndarray:
        if flc.size == 0:
            return np.zeros(0, np.float32)
        idx = (self._patch[flc].astype(np.uint16) << 8) | patch[None, :]
        # the drive's sum along each row is einsum's (feature_store._row_sums), not numpy's pairwise sum
        return np.einsum("ij->i", np.take(self._K, idx)) / self._z[flc]

    def _drive_rows(self, patch: np.ndarray, sub) -> np.ndarray:
        rows = sub.idx if sub.is_all or sub.stats_apart else np.concatenate([sub.idx, sub.sample])
        return self._drive(patch, rows)

    def _stats_drive(self, patch: np.ndarray, sub) -> np.ndarray:
        """The sample's drive over every stats_stride-th row and column of the fovea, normalised over them."""
        st, f = self.config.stats_stride, self.config.fovea
        keep = np.zeros((f, f), bool)
        keep[::st, ::st] = True  # the default retina: a ganglion fovea only
        pix = np.flatnonzero(keep)
        # C order, as the units' own rows: a float32 sum along a row depends on the order it is read in
        learned = np.ascontiguousarray(self._patch[sub.sample][:, pix])
        idx = (learned.astype(np.uint16) << 8) | patch[pix][None, :]
        return np.einsum("ij->i", np.take(self._K, idx)) / self._n[learned].sum(axis=1)

    def _decode_shared(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        g_cur, g_tgt = self.grid.encode(m), self.grid.encode(target)
        if self.config.decoder == "svc":
            return self.spatial_view_cells.decode(g_cur, g_tgt)
        zf, zt = self.grid._project(g_cur), self.grid._project(g_tgt)
        return reference_decode_phase_difference(self.grid, np.angle(zt * np.conj(zf)))

    def _sense(self, img, pos, sub, predicted):
        sub.drives.clear()  # nothing remembered: every fixation computes its drive
        cfg = self.config
        x, y = int(pos[0]), int(pos[1])
        patch = self._patch_at(img, x, y)
        T, uT, uR = self._shortlist_drive(patch, x, y, sub, predicted)
        mean, var, N = self._drive_stats(sub, T, uT, uR)
        j = int(uT.argmax())
        umax = float(uT[j])
        winner = int(T[j])
        p = -1
        if predicted >= 0:
            if T is sub.all_local:
                p = predicted
            else:
                pk = np.flatnonzero(T == predicted)
                p = int(pk[0]) if pk.size else -1
        upred = float(uT[p]) if p >= 0 else 0.0
        if not umax > mean + cfg.n_std * math.sqrt(var) or umax <= 0:
            return vm.Sense(False, winner, umax, upred=upred)
        ut = uT / umax
        mean_t, var_t = mean / umax, var / umax**2
        if p >= 0:
            old = float(ut[p])
            ut[p] = old * cfg.prediction_bias
            m2_t = var_t + mean_t**2 + (ut[p] ** 2 - old**2) / N
            mean_t = mean_t + (ut[p] - old) / N
            var_t = max(0.0, m2_t - mean_t**2)
        keep = ut >= mean_t + cfg.n_std * math.sqrt(var_t)
        if not keep.any():
            keep[int(ut.argmax())] = True
        if cfg.max_survivors and np.count_nonzero(keep) > cfg.max_survivors:
            idx = np.flatnonzero(keep)
            top = idx[np.argsort(-ut[idx], kind="stable")[: cfg.max_survivors]]
            keep = np.zeros_like(keep)
            keep[top] = True
        surv = T[keep]
        vals = ut[keep].astype(np.float64) * cfg.softmax_gain
        e = np.exp(vals - vals.max())
        wts = e / e.sum()
        best = int(surv[int(vals.argmax())])
        return vm.Sense(True, winner, umax, surv, wts, best, upred)

    def _query(self, image, candidates, prior=None, prior_activity=0.0):
        cfg = self.config
        work, scale, cimg = self._views(image)
        H, W = work.shape[:2]
        size = (int(round(W * scale)), int(round(H * scale)))
        if candidates is None:
            frames = None
        else:
            frames = np.unique(np.array([self._check_frame(c) for c in candidates], dtype=np.int64))
        sub = ReferenceSubset(self, frames)
        if sub.n == 0:
            return vm.Recognition(None, 0.0, [], 0, 0.0, size, "no stored frames")
        sense_img = self._blur(work) if cfg.query_blur else work
        starts = self._corners(cimg, cfg.query_keypoints, self.h)
        if len(starts) == 0:
            return vm.Recognition(None, 0.0, [], 0, 0.0, size, "no keypoints in the query")
        nframes = self._nframes if frames is None else frames.size
        start = self._prior(frames, prior, prior_activity)  # the frames' starting activity: no fast path there
        return vm._Query(cast(Any, sub), sense_img, starts, scale, size, nframes, start)

    def _fixate(self, q, st, a, steps, resets):
        s = self._sense(q.sense_img, st.e, q.sub, q.sub.local(st.predicted) if st.predicted >= 0 else -1)
        outcome, found = self._observe(st, s, q.sub, a)
        steps.append(
            vm.SaccadeStep(
                attempt=resets,
                fixation=cast("tuple[float, float]", _to_img(st.e, q.scale)),
                target=_to_img(st.target, q.scale),
                predicted_frame=int(self._frame[st.predicted]) if st.predicted >= 0 else None,
                predicted_feature=None if st.predicted < 0 else int(st.predicted),
                found_frame=None if found is None else int(self._frame[found]),
                found_feature=found,
                similarity=float(s.umax),
                outcome=outcome,
                evidence=reference_leading(a, self.config.trace_hypotheses),
            )
        )
        st.first = False
        return s, outcome

    def _observe(self, st, s, sub, a):
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
            g = sub.idx[s.survivors]
            np.add.at(a, self._frame[g], cfg.kappa * self._w[g] * s.weights)
            np.clip(a, 0.0, 1.0, out=a)
            if a.sum() > cfg.max_total_activity:
                st.reset_reason = "total frame activity too high"
            if st.first and cfg.anchor == "start":
                st.m = self._pos[found].astype(np.int64)
        return outcome, found

    def _choose_target(self, a, e, m, visited, rng, img, frame=-1):
        cfg = self.config
        active = np.flatnonzero(a > 0)
        if active.size == 0:
            return -1, None, None, "no frame hypothesis"
        if frame >= 0:
            active = np.array([frame])
        elif cfg.next_target != "stochastic":
            active = active[[int(np.argmax(a[active]))]]
        ks = np.concatenate([np.arange(self._fstart[f], self._fstart[f] + self._fcount[f]) for f in active])
        if cfg.next_target == "stochastic":
            v = self._w[ks] * a[self._frame[ks]] * (1.0 - rng.random(ks.size))
        elif cfg.next_target == "most_active":
            v = 0.5 + 0.5 * rng.random(ks.size)
        else:
            v = 1.0 / (1.0 + np.abs(self._pos[ks] - m[None, :]).sum(axis=1))
        if visited:
            vis = set(visited)
            v[[i for i, k in enumerate(ks.tolist()) if k in vis]] = 0.0
        order = np.argsort(-v, kind="stable")
        order = order[v[order] > 0][: cfg.target_candidates]
        if order.size == 0:
            return -1, None, None, "no feature left to predict"
        tol = cfg.tolerance_px
        mf = m.astype(float)
        for j in order.tolist():
            k = int(ks[j])
            d = self._decode_shared(mf, self._pos[k].astype(float))
            dx, dy = int(d[0]), int(d[1])
            if abs(dx) <= tol and abs(dy) <= tol:
                continue
            tgt = e + d
            land = self._microsaccade(img, tgt, k, float(np.hypot(dx, dy)))
            if land is None:
                if cfg.out_of_view == "skip":
                    continue
                return -1, None, None, "saccade out of the image"
            return k, tgt, land, ""
        return -1, None, None, "no feature left to predict"

    def _views(self, image):
        gray, work, scale = vm.prepare_views(image, self.config)
        cimg = work if self.config.corner_source == "retina" else imadjust(gray, self.config.contrast_clip)
        return work, scale, cimg


def perturb(img: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = img.astype(np.float64) * 0.85 + 25 + rng.normal(0.0, 8.0, img.shape)
    return np.roll(np.clip(q, 0, 255).astype(np.uint8), (3, 5), axis=(0, 1))


SCENES = [shapes_scene(s) for s in range(10)]
QUERIES = [(perturb(SCENES[f], seed=f), None) for f in (0, 4, 9)] + [
    (shapes_scene(4000), None),  # never learned: every reset is used
    (perturb(SCENES[6], seed=11), [5, 6, 7]),
    (perturb(SCENES[2], seed=12), [7, 8]),  # the right frame is not a candidate
    (SCENES[3], None),  # the learned image itself
    (perturb(SCENES[5], seed=13), [1, 2, 3, 4, 5, 6, 7, 8]),  # with the index: more candidates than it scores
]


def _pair(cfg: VisualConfig) -> tuple[vm.VisualMemory, ReferenceMemory]:
    fast, ref = vm.VisualMemory(cfg), ReferenceMemory(cfg)
    for img in SCENES:
        assert fast.learn(img) == ref.learn(img)
    return fast, ref


def _same_state(a: vm.VisualMemory, b: vm.VisualMemory) -> None:
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        if isinstance(sa[k], np.ndarray):
            assert np.array_equal(sa[k], sb[k]), k
        else:
            assert sa[k] == sb[k], k


@pytest.mark.parametrize(
    "override",
    [
        {},
        {"index_shortlist": 12, "stats_sample": 16},
        {"decoder": "svc"},
        {"anchor": "none"},
        {"next_target": "stochastic"},
        {"next_target": "most_active"},
        {"out_of_view": "skip", "n_std": 1.0, "max_survivors": 3},
        {"microsaccade_gain": 0.2},
    ],
    ids=["exact", "index", "svc", "no-anchor", "stochastic", "most-active", "skip-many-survivors", "wide-microsaccade"],
)
def test_recognitions_equal_the_reference_bit_for_bit(override):
    fast, ref = _pair(VisualConfig(**override))
    if "index_shortlist" in override:
        n_index = fast.config.index_shortlist + fast.config.stats_sample
        assert fast.n_features > n_index  # the index is used
        assert sum(fast._fcount[QUERIES[-1][1]]) > n_index  # also with candidates
    outcomes = set()
    for _ in range(2):  # twice: the second pass meets remembered decodes
        for img, cands in QUERIES:
            a = fast.recognise(img, candidates=cands).to_dict()
            b = ref.recognise(img, candidates=cands).to_dict()
            assert a == b
            outcomes.add(a["frame_id"] is not None)
    assert outcomes == {True, False}  # both accepted and rejected recognitions were compared
    _same_state(fast, ref)


def test_primed_recognitions_equal_the_reference_bit_for_bit():
    """With a prior (docs/MODEL.md item 115) the fast paths still give the reference's recognitions; a prior on the
    first candidates changes some of them (the head start acts), and a prior of 0 changes none."""
    fast, ref = _pair(VisualConfig())
    changed = 0
    for img, cands in QUERIES:
        prior = list(cands[:2]) if cands else [0, 1]
        a = fast.recognise(img, candidates=cands, prior=prior, prior_activity=0.3).to_dict()
        assert a == ref.recognise(img, candidates=cands, prior=prior, prior_activity=0.3).to_dict()
        plain = ref.recognise(img, candidates=cands).to_dict()
        zero = ref.recognise(img, candidates=cands, prior=prior, prior_activity=0.0).to_dict()
        changed += a != plain
        assert zero == plain
    assert changed > 0
    _same_state(fast, ref)


def test_recognise_then_learn_the_same_frame_equals_the_reference():
    """The mapper's key-frame pattern: the retina views of a recognised frame are reused to learn it."""
    fast, ref = _pair(VisualConfig())
    for img, cands in QUERIES[:3]:
        assert fast.recognise(img, candidates=cands).to_dict() == ref.recognise(img, candidates=cands).to_dict()
        assert fast.learn(img) == ref.learn(img)
    _same_state(fast, ref)
    img = QUERIES[4][0].copy()
    fast.recognise(img)
    ref.recognise(img)
    img[40:120, 60:200] = 255 - img[40:120, 60:200]  # the caller reuses its buffer for another picture
    assert fast.learn(img) == ref.learn(img)
    _same_state(fast, ref)
    assert fast.recognise(img).to_dict() == ref.recognise(img).to_dict()


def test_a_point_fixated_again_reuses_its_drive(monkeypatch):
    """A saccade that lands on a point fixated before in the same recognition gets the drive
    remembered there (read only), not a second gather; the results equal the reference (above).
    [BBc]'s 10 resets: enough attempts on this never-learned scene for one to fixate a point again."""
    fast, ref = _pair(VisualConfig(max_resets=10))
    calls = {"sense": 0, "drive": 0}
    sense, drive = vm.VisualMemory._sense, vm.VisualMemory._drive_rows

    def count_sense(self, *a):
        calls["sense"] += 1
        return sense(self, *a)

    def count_drive(self, *a):
        calls["drive"] += 1
        return drive(self, *a)

    monkeypatch.setattr(vm.VisualMemory, "_sense", count_sense)
    monkeypatch.setattr(vm.VisualMemory, "_drive_rows", count_drive)
    img = shapes_scene(4001)  # never learned: every reset is used, and a point is fixated twice
    a = fast.recognise(img).to_dict()
    assert 0 < calls["drive"] < calls["sense"]
    fixations = [tuple(st["fixation"]) for st in a["steps"]]
    assert calls["drive"] == len(set(fixations))  # one gather per distinct point
    monkeypatch.undo()
    assert a == ref.recognise(img).to_dict()


def test_remembered_decodes_are_private_copies():
    mem = vm.VisualMemory()
    m, t = np.array([40.0, 50.0]), np.array([200.0, 130.0])
    d = mem._decode(m, t)
    assert d.tolist() == [160, 80]
    d[:] = 0  # the caller may change what it got
    assert mem._decode(m, t).tolist() == [160, 80]
    assert np.array_equal(mem._decode(m, t), ReferenceMemory()._decode(m, t))


@pytest.mark.parametrize("lut16", [True, False], ids=["opencv-lut", "numpy-take"])
def test_table_gather_equals_numpy_take(monkeypatch, lut16):
    if lut16 and not feature_store._LUT16:
        pytest.skip("this OpenCV has no 16-bit LUT")
    monkeypatch.setattr(feature_store, "_LUT16", lut16)
    rng = np.random.default_rng(0)
    table = rng.normal(size=65536).astype(np.float32)
    idx = rng.integers(0, 65536, size=(37, 961)).astype(np.uint16)
    idx[0, :2] = (0, 65535)
    out = feature_store._gather_k(table, idx)
    assert out.dtype == np.float32 and out.shape == idx.shape
    assert np.array_equal(out, np.take(table, idx))


def test_trace_step_dict_equals_dataclasses_asdict():
    step = vm.SaccadeStep(
        attempt=1,
        fixation=(3.0, 4.5),
        target=None,
        predicted_frame=2,
        predicted_feature=17,
        found_frame=None,
        found_feature=None,
        similarity=0.25,
        outcome="no_evidence",
        evidence=[(2, 0.5), (0, 0.125)],
        event="reset: x",
    )
    ref = dataclasses.asdict(step)
    ref["fixation"], ref["target"] = [3.0, 4.5], None
    ref["evidence"] = [[2, 0.5], [0, 0.125]]
    got = step.to_dict()
    assert got == ref and list(got) == list(ref)


@pytest.mark.parametrize(
    "freqs", [None, (0.0211, 0.0151, 0.0108, 0.0077, 0.0055, 0.004, 0.0028, 0.002, 0.0014)], ids=["default", "reversed"]
)
def test_one_pair_decode_equals_the_batched_expressions(freqs):
    """The one-pair decode (its own path, scalar steps and one cosine per cost) gives what the batched
    expressions give for that pair, for points on and off the working view, for noisy grid states, and
    with the coarse modules not first (a gather, not a slice)."""
    grid = VisualGridCells(VisualConfig() if freqs is None else VisualConfig(vgc_frequencies=freqs))
    rng = np.random.default_rng(7)
    a = np.concatenate([rng.integers(16, 304, (3000, 2)), rng.integers(-60, 420, (1000, 2))]).astype(float)
    b = np.concatenate([rng.integers(16, 304, (3000, 2)), rng.integers(-60, 420, (1000, 2))]).astype(float)
    ga, gb = grid.encode(a), grid.encode(b)
    noisy = slice(0, 1000)  # the first thousand pairs again with sigma 0.1 noise on both grid states
    ga = np.concatenate([ga, ga[noisy] + rng.normal(0.0, 0.1, ga[noisy].shape)])
    gb = np.concatenate([gb, gb[noisy] + rng.normal(0.0, 0.1, gb[noisy].shape)])
    za, zb = grid._project(ga), grid._project(gb)
    deltas = np.angle(zb * np.conj(za))
    for d in deltas:
        assert np.array_equal(grid.decode_phase_difference(d), reference_decode_phase_difference(grid, d))


def test_mean_var_equals_numpy():
    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 128, 1000):
        u = (rng.random(n) * 10.0 ** rng.integers(-3, 4)).astype(np.float32).astype(np.float64)
        assert feature_store._mean_var(u) == (float(u.mean()), float(u.var()))


def test_learning_after_recognition_reuses_the_query_corners(monkeypatch):
    """Learning a frame just recognised takes the leading corners of the query's (one corner search)."""
    fast, ref = _pair(VisualConfig())
    img = QUERIES[0][0]
    ref.recognise(img)
    fid = ref.learn(img)
    calls = {"n": 0}
    gftt = feature_store.cv2.goodFeaturesToTrack

    def count(*a, **k):
        calls["n"] += 1
        return gftt(*a, **k)

    monkeypatch.setattr(feature_store.cv2, "goodFeaturesToTrack", count)
    fast.recognise(img)
    assert calls["n"] == 1
    assert fast.learn(img) == fid
    assert calls["n"] == 1
    _same_state(fast, ref)


def test_leading_frames_equal_the_reference():
    rng = np.random.default_rng(5)
    for n in (1, 3, 40, 300):
        for _ in range(200):
            a = rng.random(n) * (rng.random(n) < 0.3)
            a[rng.integers(0, n, 2)] = a.max()  # ties
            for k in (1, 5):
                got, ref = vm._leading(a, k), reference_leading(a, k)
                assert got == ref and [type(x) for t in got for x in t] == [type(x) for t in ref for x in t]


def reference_shift_summary(correspondences):
    if not correspondences:
        return None
    d = np.array([[c["query"][0] - c["memory"][0], c["query"][1] - c["memory"][1]] for c in correspondences], float)
    med = np.median(d, axis=0)
    mad = np.median(np.abs(d - med), axis=0)
    return {"x": float(med[0]), "y": float(med[1]), "mad_x": float(mad[0]), "mad_y": float(mad[1]), "n": int(len(d))}


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_shift_summary_equals_numpy_median():
    """The shift summary is np.median's median and MAD of the correspondences, bit for bit, signed zeros, NaN
    and infinities included: a faster median must keep exactly these values."""
    rng = np.random.default_rng(9)
    special = [0.0, -0.0, 1.0, 2.5, np.nan, np.inf, -np.inf]
    for it in range(3000):
        n = int(rng.integers(1, 12))
        if it % 3 == 0:
            q, m = rng.integers(0, 320, (n, 2)) * 1.0, rng.integers(0, 320, (n, 2)) * 1.0
        elif it % 3 == 1:
            q, m = rng.normal(size=(n, 2)) * 50, rng.integers(0, 3, (n, 2)) * 0.5
        else:
            q, m = rng.choice(special, (n, 2)), rng.choice(special[:4], (n, 2))
        corr = [{"query": [float(a[0]), float(a[1])], "memory": [float(b[0]), float(b[1])]} for a, b in zip(q, m)]
        assert repr(vm.shift_summary(corr)) == repr(reference_shift_summary(corr))
    assert vm.shift_summary([]) is None


@pytest.mark.parametrize("n_frames", [3, 10, 40])
def test_subsets_equal_the_reference(n_frames):
    """A subset's rows, their de-duplication and gathered patches equal those built by np.unique for the
    subset alone, whether the library is small (its sample is every unit), large, or indexed."""
    mem = vm.VisualMemory(VisualConfig())
    for i in range(n_frames):
        mem.learn(shapes_scene(100 + i))
    rng = np.random.default_rng(n_frames)
    choices = [None, np.arange(mem.n_frames)] + [
        np.unique(rng.integers(0, mem.n_frames, int(rng.integers(1, mem.n_frames + 1)))) for _ in range(20)
    ]
    for frames in choices:
        for _ in range(2):  # the second subset of the same library reads what the first remembered
            got, ref = feature_store.FlcSubset(mem, frames), ReferenceSubset(mem, frames)
            assert np.array_equal(got.idx, ref.idx) and got.n == ref.n and got.exact_all == ref.exact_all
            assert np.array_equal(got.desc, ref.desc)
            assert (got.sample is None) == (ref.sample is None)
            if ref.sample is not None:
                assert np.array_equal(got.sample, ref.sample)
            if ref.exact_all:
                assert np.array_equal(got.rows, ref.rows)
                assert (got.rows_inv is None) == (ref.rows_inv is None)
                if ref.rows_inv is not None:
                    assert np.array_equal(got.rows_inv, ref.rows_inv)
                assert np.array_equal(got.rows_hi, ref.rows_hi) and got.rows_hi.dtype == np.uint16
                assert np.array_equal(got.rows_z, ref.rows_z)
            assert got.stats_apart == ref.stats_apart
            if ref.stats_apart:  # the sample at every second row and column of the fovea (stats_stride 2)
                keep = np.zeros((31, 31), bool)
                keep[::2, ::2] = True
                learned = np.ascontiguousarray(mem._patch[ref.sample][:, np.flatnonzero(keep)])
                assert np.array_equal(got.stats_hi, learned.astype(np.uint16) << 8)
                assert np.array_equal(got.stats_z, mem._n[learned].sum(axis=1))
            for g in (0, mem.n_features - 1, int(got.idx[-1]), int(rng.integers(0, mem.n_features))):
                assert got.local(g) == ref.local(g)


def test_candidate_ids_are_checked_like_one_by_one():
    mem = vm.VisualMemory(VisualConfig())
    for i in range(4):
        mem.learn(shapes_scene(200 + i))
    for cands in ([3, 1, 1, 0], [np.int64(2), 0], [True, 2], [2.0, 1], (1, 3), range(4)):
        assert np.array_equal(mem._candidate_frames(cands), np.unique([mem._check_frame(c) for c in cands]))
    for bad in ([4], [-1, 2], [1, 2.5], [2**70], ["1"]):
        with pytest.raises(InputError):
            mem._candidate_frames(bad)


def test_one_point_phase_code_equals_encode_then_project():
    """The saccade loop's phasors of one point are those of the public encode and projection, bit for bit."""
    grid = VisualGridCells()
    rng = np.random.default_rng(11)
    for p in np.concatenate([rng.integers(-60, 420, (300, 2)), rng.random((100, 2)) * 400]).astype(float):
        assert np.array_equal(grid._phase_code_one(p), grid._project(grid.encode(p)))
