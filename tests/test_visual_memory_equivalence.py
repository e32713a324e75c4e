"""The visual memory's fast paths give exactly what the straightforward computation gives.

:class:`ReferenceMemory` keeps, in this file, the plain implementation of every part the fast code
replaces: the FLC drive as one ``np.take`` over freshly gathered patches for every fixation, the
saccade vector decoded from the two grid codes every time, the retina run on every call, no drive
remembered per fixation point, and ``dataclasses.asdict`` for a trace step. Recognitions (winning
frame, evidence, every step of the saccade trace, correspondences) and the learned state must be
identical, bit for bit, for the exact path, the index path, candidate subsets, a decoder variant
and rejected queries.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hippomap import feature_store
from hippomap import visual_memory as vm
from hippomap.config import VisualConfig
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


class ReferenceMemory(vm.VisualMemory):
    """The memory with its fast paths replaced by the plain computation they must equal."""

    def _drive(self, patch: np.ndarray, flc: np.ndarray) -> np.ndarray:
        if flc.size == 0:
            return np.zeros(0, np.float32)
        idx = (self._patch[flc].astype(np.uint16) << 8) | patch[None, :]
        return np.take(self._K, idx).sum(axis=1) / self._z[flc]

    def _drive_rows(self, patch: np.ndarray, sub) -> np.ndarray:
        rows = sub.idx if sub.is_all else np.concatenate([sub.idx, sub.sample])
        return self._drive(patch, rows)

    def _drive_index(self, patch: np.ndarray, sub, flc: np.ndarray) -> np.ndarray:
        return self._drive(patch, np.concatenate([flc, sub.sample]))

    def _decode_shared(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        g_cur, g_tgt = self.grid.encode(m), self.grid.encode(target)
        if self.config.decoder == "svc":
            return self.spatial_view_cells.decode(g_cur, g_tgt)
        zf, zt = self.grid._project(g_cur), self.grid._project(g_tgt)
        return reference_decode_phase_difference(self.grid, np.angle(zt * np.conj(zf)))

    def _sense(self, img, pos, sub, predicted):
        sub.drives.clear()  # nothing remembered: every fixation computes its drive
        return super()._sense(img, pos, sub, predicted)

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
    ],
    ids=["exact", "index", "svc", "no-anchor", "stochastic"],
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
    remembered there (read only), not a second gather; the results equal the reference (above)."""
    fast, ref = _pair(VisualConfig())
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
    """The one-pair decode (its own path) gives what the batched expressions give for that pair, for
    points on and off the working view, and with the coarse modules not first (a gather, not a slice)."""
    grid = VisualGridCells(VisualConfig() if freqs is None else VisualConfig(vgc_frequencies=freqs))
    rng = np.random.default_rng(7)
    a = np.concatenate([rng.integers(16, 304, (3000, 2)), rng.integers(-60, 420, (1000, 2))]).astype(float)
    b = np.concatenate([rng.integers(16, 304, (3000, 2)), rng.integers(-60, 420, (1000, 2))]).astype(float)
    za, zb = grid._project(grid.encode(a)), grid._project(grid.encode(b))
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
