"""The visual memory's feature store: feature label cells (FLCs), their frames, drive and index.

Learning one-shot (:meth:`FeatureStore.learn`, [BBc] adapted to key frames): a frame's fixation
points (top Shi-Tomasi corners, or random points as in [S]) become FLCs whose sensory weights are
the Gaussian-tuned response of the sensory cells to the *blurred* fovea patch, connected to a new
frame node. Storage is struct-of-arrays, grown by doubling.

An FLC's drive ``u_k = W_k . s(I)`` reduces exactly to ``sum_p K[I~_{k,p}, I_p] / Z_k`` with the
256 x 256 table ``K = S S^T`` of the sensory cells (:meth:`FeatureStore._drive`): the sensory
cells are simulated exactly but never materialised. Above ``index_shortlist + stats_sample`` FLCs
an index is used (:meth:`FeatureStore._shortlist_drive`): OpenCV's ``batchDistance`` finds the
``index_shortlist`` nearest 8 x 8 area-averaged patch descriptors, whose drive is computed
exactly, and the population's statistics (the ``N_std`` rule) are estimated from them plus a fixed
stratified sample of ``stats_sample`` other units, driven over every ``stats_stride``-th row and column
of their foveae. :class:`~hippomap.flc_subset.FlcSubset` is the
set of FLCs one recognition may use (all, or the candidate frames').

The saccade loop that reads this store is :class:`~hippomap.visual_memory.VisualMemory`.
"""

from __future__ import annotations

from typing import Any, Self

import cv2
import numpy as np

from .config import VisualConfig
from .errors import InputError
from .flc_subset import FlcSubset, _Library
from .retina import imadjust
from .visual_images import prepare_views, working_size

__all__ = ["FeatureStore", "FlcSubset", "STATE_VERSION"]

STATE_VERSION = 1


def _lut16_works() -> bool:
    """Whether this OpenCV's ``LUT`` takes a 65,536-entry table indexed by uint16 (OpenCV >= 5)."""
    try:
        out = cv2.LUT(np.array([[0, 65535]], np.uint16), np.arange(65536, dtype=np.float32).reshape(1, -1))
    except cv2.error:
        return False
    return out.dtype == np.float32 and out.tolist() == [[0.0, 65535.0]]


_LUT16 = _lut16_works()


def _channel0(img: np.ndarray) -> np.ndarray:
    """The ganglion (centre-surround) image of a sensory image with or without orientation channels."""
    return img[..., 0] if img.ndim == 3 else img


def _gather_k(table: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``table[idx]`` for a flat float32 table of 65,536 entries and a 2-D uint16 index array.

    OpenCV's 16-bit ``LUT`` reads the uint16 indices directly; ``np.take`` first converts them all to
    64-bit integers, which costs more than the gather itself. The values are the same either way."""
    if _LUT16 and idx.ndim == 2 and idx.dtype == np.uint16:
        return cv2.LUT(idx, table.reshape(1, -1))
    return np.take(table, idx)


def _row_sums(g: np.ndarray) -> np.ndarray:
    """The sum of each row of a 2-D float32 array (float32, one per row): ``einsum('ij->i')``, which
    adds along each row in one vectorised pass, about three times as fast as numpy's pairwise
    ``sum(axis=1)`` on a fixation's few hundred rows of a fovea's 961 values, within about 2e-7 of
    the exact sum (the pairwise sum: about 1e-7), far below what tells two units apart. A row's sum
    depends only on its values, never on the other rows or where the row lies in memory, so a unit
    driven in two places of a fixation gets one drive. (OpenCV's row reduction is as fast on one
    thread but spreads over OpenCV's threads, whose waiting costs more CPU than it saves.)"""
    return np.einsum("ij->i", g)


def _mean_var(u: np.ndarray) -> tuple[float, float]:
    """``(u.mean(), u.var())`` of a non-empty float64 vector, as floats, by the operations numpy runs for
    them (the pairwise sum divided by the count; the sum of the squared deviations from that mean divided
    by the count), without their wrappers' overhead: the same numbers bit for bit."""
    n = u.size
    mean = np.add.reduce(u) / n
    d = u - mean
    return float(mean), float(np.add.reduce(np.multiply(d, d, out=d)) / n)


class FeatureStore:
    """The FLCs of the learned key frames, their frames, and their drive by a fovea patch."""

    def __init__(self, config: VisualConfig | None = None):
        self.config = cfg = config or VisualConfig()
        if cfg.fovea % 2 == 0:
            raise InputError(f"fovea must be odd (2h+1), got {cfg.fovea}")
        self.h = cfg.fovea // 2
        # a feature unit's sensory field: the fovea of the ganglion image, then the fovea of each
        # orientation channel sampled every v1_stride px (prepare_views stacks them in this order)
        self.P0 = cfg.fovea * cfg.fovea
        self._n_ori = cfg.v1_orientations if cfg.retina_mode != "none" else 0
        self._ori_side = len(range(0, cfg.fovea, cfg.v1_stride))
        self.P = self.P0 + self._n_ori * self._ori_side**2
        self.D = cfg.index_side * cfg.index_side
        self._stats_pix = self._stride_pixels(cfg.stats_stride)  # where the statistics sample is driven
        # sensory cells: s_a(v) = exp(-((a - v)/sigma)^2), cut below the cutoff ([BBc])
        v = np.arange(256, dtype=np.float64)
        S = np.exp(-(((v[:, None] - v[None, :]) / cfg.sensory_sigma) ** 2))
        S[S < cfg.sensory_cutoff] = 0.0
        self._K = (S @ S.T).astype(np.float32).ravel()  # K[a, b] flattened, a = learned, b = seen
        self._n = S.sum(axis=1).astype(np.float32)  # sum_v s_a(v)
        self._rng = np.random.default_rng(cfg.seed)
        self._last_views: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None  # see _views
        self._last_corners: tuple[np.ndarray, float, int, np.ndarray] | None = None  # see _corners
        self._lib: _Library | None = None  # see _library
        cap = 64
        self._patch = np.zeros((cap, self.P), np.uint8)
        self._desc = np.zeros((cap, self.D), np.float32)
        self._z = np.zeros(cap, np.float32)
        self._pos = np.zeros((cap, 2), np.int32)
        self._frame = np.zeros(cap, np.int32)
        self._w = np.zeros(cap, np.float32)
        self._nf = 0
        fcap = 16
        self._fstart = np.zeros(fcap, np.int64)
        self._fcount = np.zeros(fcap, np.int64)
        self._fsize = np.zeros((fcap, 2), np.int32)
        self._fscale = np.ones(fcap, np.float32)  # input px per working px of each learned frame
        self._nframes = 0

    # -- sizes ------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return self._nframes

    @property
    def n_features(self) -> int:
        return self._nf

    @property
    def frame_count(self) -> int:
        """Alias of :attr:`n_frames` (used by :mod:`hippomap.mapper`)."""
        return self._nframes

    def check_image(self, image: Any, name: str = "image") -> None:
        """Raise :class:`InputError` if ``image`` could not be learned or recognised (no state change).
        Only the checks: the retina runs when a key frame is recognised or learned, not on every frame."""
        working_size(image, self.config, name)

    def __len__(self) -> int:
        return self._nframes

    def memory_bytes(self) -> int:
        """Bytes held per the stored arrays (used part, not the preallocated capacity)."""
        n, f = self._nf, self._nframes
        per_flc = self.P + self.D * 4 + 4 + 8 + 4 + 4  # patch, descriptor, Z, position, frame, W_FLC->ID
        return n * per_flc + f * (8 + 8 + 8 + 4)

    def frame_features(self, frame_id: int) -> dict[str, np.ndarray]:
        """The learned fixation points (working px, learning order) and FLC ids of a frame."""
        fid = self._check_frame(frame_id)
        s, c = int(self._fstart[fid]), int(self._fcount[fid])
        return {"features": np.arange(s, s + c), "points": self._pos[s : s + c].copy(), "size": self._fsize[fid].copy()}

    def _check_frame(self, frame_id: Any) -> int:
        try:
            fid = int(frame_id)
        except (TypeError, ValueError):
            raise InputError(f"frame id must be an integer, got {frame_id!r}") from None
        if fid != frame_id or not 0 <= fid < self._nframes:
            raise InputError(f"unknown frame id {frame_id!r}; the memory holds frames 0..{self._nframes - 1}")
        return fid

    def _library(self) -> _Library:
        """What the subsets of the current library share (:class:`_Library`), remembered per library size."""
        lib = self._lib
        if lib is None or lib.n != self._nf:
            lib = self._lib = _Library(self)
        return lib

    # -- views and patches -------------------------------------------------------------
    def _views(self, image: Any) -> tuple[np.ndarray, float, np.ndarray]:
        """``(work, scale, corner image)`` of a frame: :func:`prepare_views`, then the image whose corners
        become fixation points (``corner_source``).

        The mapper recognises a key frame and then learns the same frame: the views of the last frame
        are kept with a copy of it, and a frame equal to it (same shape, dtype and pixels) gets them
        again instead of another pass through the retina. The kept arrays are read-only."""
        cfg = self.config
        last = self._last_views
        if (
            last is not None
            and isinstance(image, np.ndarray)
            and image.shape == last[0].shape
            and image.dtype == last[0].dtype
            and np.array_equal(image, last[0])
        ):
            return last[1], last[2], last[3]
        gray, work, scale = prepare_views(image, cfg)
        cimg = _channel0(work) if cfg.corner_source == "retina" else imadjust(gray, cfg.contrast_clip)
        for a in (work, cimg):
            a.flags.writeable = False
        self._last_views = (np.array(image, copy=True), work, scale, cimg)
        return work, scale, cimg

    def _stride_pixels(self, stride: int) -> np.ndarray | None:
        """Positions in a sensory field (``P`` values, :meth:`_patch_at`'s order) of every ``stride``-th row
        and column of the ganglion fovea and of each orientation channel's fovea; None when ``stride`` is 1."""
        f, o = self.config.fovea, self._ori_side
        grids = [(np.arange(0, f, stride)[:, None] * f + np.arange(0, f, stride)).ravel()]
        grids += [
            self.P0 + c * o * o + (np.arange(0, o, stride)[:, None] * o + np.arange(0, o, stride)).ravel()
            for c in range(self._n_ori)
        ]
        return None if stride == 1 else np.concatenate(grids)

    def _descriptor(self, patches: np.ndarray) -> np.ndarray:
        f, s = self.config.fovea, self.config.index_side
        out = np.empty((patches.shape[0], self.D), np.float32)
        for i, p in enumerate(patches[:, : self.P0].reshape(-1, f, f)):  # the ganglion part indexes
            out[i] = cv2.resize(p, (s, s), interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
        return out

    def _blur(self, img: np.ndarray) -> np.ndarray:
        b = self.config.blur
        return cv2.blur(img, (b, b), borderType=cv2.BORDER_REFLECT) if b > 1 else img

    def _margin(self) -> int:
        return self.h + 1

    def _corners(self, img: np.ndarray, k: int, min_dist: float) -> np.ndarray:
        """The ``k`` strongest Shi-Tomasi corners of ``img`` at least ``min_dist`` apart (int32 (n, 2)).

        A key frame is recognised (``query_keypoints`` corners, sometimes twice) and then learned
        (``n_fixations`` corners) from the same kept corner image (:meth:`_views`, read only): the
        corners of the last such image are remembered, and a request for as many or fewer of them
        gets their leading rows. That is exact: OpenCV sorts the candidate corners once (by response,
        ties by position) and accepts them greedily in that order until it has ``maxCorners``, so the
        first ``k`` of a longer run are the corners of a run asked for ``k``."""
        last = self._last_corners
        if last is not None and last[0] is img and last[1] == min_dist and (k <= last[2] or len(last[3]) < last[2]):
            return last[3][:k].copy()
        m = self._margin()
        H, W = img.shape
        mask = np.zeros_like(img)
        mask[m : H - m, m : W - m] = 255
        pts = cv2.goodFeaturesToTrack(
            img,
            maxCorners=int(k),
            qualityLevel=self.config.corner_quality,
            minDistance=float(min_dist),
            mask=mask,
            blockSize=self.config.corner_block,
        )
        if pts is None:
            out = np.zeros((0, 2), np.int32)
        else:
            out = np.rint(pts.reshape(-1, 2)).astype(np.int32)
        if not img.flags.writeable:  # a kept view (nobody changes it in place): remember its corners
            self._last_corners = (img, float(min_dist), int(k), out.copy())
        return out

    def _random_points(self, shape: tuple[int, int], k: int) -> np.ndarray:
        m = self._margin()
        H, W = shape[:2]
        cand = self._rng.integers([m, m], [W - m, H - m], size=(40 * k, 2))
        chosen: list[np.ndarray] = []
        for c in cand:  # k accepted points: a tiny loop, not a hot path
            if all(np.abs(c - q).max() >= self.h for q in chosen):
                chosen.append(c)
                if len(chosen) == k:
                    break
        return np.array(chosen, np.int32).reshape(-1, 2)

    def _patch_at(self, img: np.ndarray, x: int, y: int) -> np.ndarray:
        """The sensory field of a fovea at (x, y): ganglion fovea, then each orientation channel's
        fovea sampled every ``v1_stride`` px (``P`` uint8 values)."""
        h = self.h
        if img.ndim == 2:
            return img[y - h : y + h + 1, x - h : x + h + 1].ravel()
        st = self.config.v1_stride
        g = img[y - h : y + h + 1, x - h : x + h + 1, 0].ravel()
        o = img[y - h : y + h + 1 : st, x - h : x + h + 1 : st, 1:]
        return np.concatenate([g, o.transpose(2, 0, 1).ravel()])

    def _patches(self, img: np.ndarray, pts: np.ndarray) -> np.ndarray:
        return (
            np.stack([self._patch_at(img, int(x), int(y)) for x, y in pts])
            if len(pts)
            else np.zeros((0, self.P), np.uint8)
        )

    def _reserve(self, n_features: int, n_frames: int) -> None:
        """Grow the arrays (doubling) to hold at least this many feature units and frames."""
        if n_features > self._patch.shape[0]:
            cap = max(n_features, 2 * self._patch.shape[0])
            for name in ("_patch", "_desc", "_z", "_pos", "_frame", "_w"):
                a = getattr(self, name)
                b = np.zeros((cap,) + a.shape[1:], a.dtype)
                b[: self._nf] = a[: self._nf]
                setattr(self, name, b)
        if n_frames > self._fstart.shape[0]:
            cap = max(n_frames, 2 * self._fstart.shape[0])
            for name in ("_fstart", "_fcount", "_fsize", "_fscale"):
                a = getattr(self, name)
                b = np.zeros((cap,) + a.shape[1:], a.dtype)
                b[: self._nframes] = a[: self._nframes]
                setattr(self, name, b)

    # -- learning ----------------------------------------------------------------------
    def learn(self, image: Any) -> int | None:
        """Learn a key frame one-shot; returns its frame id, or ``None`` when fewer than
        ``min_fixations`` fixation points were found (textureless frame, spec §2)."""
        cfg = self.config
        work, in_scale, cimg = self._views(image)
        if cfg.fixation_mode == "corners":
            pts = self._corners(cimg, cfg.n_fixations, cfg.min_distance if cfg.min_distance else self.h)
        else:
            pts = self._random_points(work.shape, cfg.n_fixations)
        if len(pts) < cfg.min_fixations:
            return None
        pts = pts[self._rng.permutation(len(pts))]  # learned in random order ([BBc] randperm)
        blurred = self._blur(work)
        patches = self._patches(blurred, pts)
        k = len(pts)
        self._reserve(self._nf + k, self._nframes + 1)
        s = self._nf
        fid = self._nframes
        self._patch[s : s + k] = patches
        desc = self._descriptor(patches)
        self._desc[s : s + k] = desc
        self._z[s : s + k] = self._n[patches].sum(axis=1)
        self._pos[s : s + k] = pts
        self._frame[s : s + k] = fid
        self._w[s : s + k] = 1.0 - self._rng.uniform(0.0, cfg.weight_jitter, k)
        self._fstart[fid] = s
        self._fcount[fid] = k
        self._fsize[fid] = (work.shape[1], work.shape[0])
        self._fscale[fid] = in_scale
        self._nf += k
        self._nframes += 1
        return fid

    # -- drive -------------------------------------------------------------------------
    def _drive(self, patch: np.ndarray, flc: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Exact FLC drive u_k of a fovea patch (uint8, P) for global FLC indices ``flc``; ``out``: a
        uint16 buffer of at least ``flc.size`` rows for the table indices (else a new array)."""
        if flc.size == 0:
            return np.zeros(0, np.float32)
        # flat index a * 256 + b into K in uint16 (fast gather; 255 * 256 + 255 fits; left_shift casts)
        buf = None if out is None else out[: flc.size]
        idx = np.left_shift(np.take(self._patch, flc, axis=0), 8, out=buf, dtype=np.uint16)
        np.bitwise_or(idx, patch[None, :], out=idx)
        return _row_sums(_gather_k(self._K, idx)) / self._z[flc]

    def _drive_rows(self, patch: np.ndarray, sub: FlcSubset) -> np.ndarray:
        """:meth:`_drive` of ``sub.rows`` from the subset's gathered patches (same numbers, no row gather).

        Each row's drive is its own gather and its own sum along the row (:func:`_row_sums`), so a row
        gathered once for a candidate that is also in the statistics sample has the same value in both places."""
        if sub.rows is None or sub.rows.size == 0:
            return np.zeros(0, np.float32)
        idx = np.bitwise_or(sub.rows_hi, patch[None, :], out=sub.rows_buf)
        u = _row_sums(_gather_k(self._K, idx)) / sub.rows_z
        return u if sub.rows_inv is None else u[sub.rows_inv]

    def _stats_drive(self, patch: np.ndarray, sub: FlcSubset) -> np.ndarray:
        """The drive of the statistics sample apart from the exactly scored units (``sub.stats_apart``): each
        row its own gather and sum over the statistics pixels (``stats_stride``), divided by its normaliser
        over the same pixels (docs/MODEL.md item 106)."""
        q = patch if self._stats_pix is None else patch[self._stats_pix]
        idx = np.bitwise_or(sub.stats_hi, q[None, :], out=sub.stats_buf)
        return _row_sums(_gather_k(self._K, idx)) / sub.stats_z

    def _exact_drive(self, patch: np.ndarray, x: int, y: int, sub: FlcSubset) -> tuple[np.ndarray, np.ndarray | None]:
        """``(uT, uR)`` of a subset scored exactly at fixation (x, y): the drive of every unit and of the
        statistics sample (None: the whole library), remembered per point for the recognition (read only)."""
        got = sub.drives.get((x, y))
        if got is None:
            u = self._drive_rows(patch, sub)
            u.flags.writeable = False
            if sub.stats_apart:
                uR = self._stats_drive(patch, sub)
                uR.flags.writeable = False
                got = (u, uR)
            elif sub.is_all:
                got = (u, None)
            else:  # a small library: the sample is every unit, driven exactly with the candidates
                got = (u[: sub.n], u[sub.n :])
            sub.drives[(x, y)] = got
        return got

    def _shortlist_drive(
        self, patch: np.ndarray, x: int, y: int, sub: FlcSubset, predicted: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(T, uT, uR)``: the local indices ``T`` of the FLCs whose drive is computed exactly at
        fixation (x, y) (all of the subset, or the index's shortlist plus the ``predicted`` unit),
        their drive ``uT``, and the drive ``uR`` of the statistics sample (None: the subset is the
        whole library, computed exactly)."""
        cfg = self.config
        if sub.exact_all:
            uT, uR = self._exact_drive(patch, x, y, sub)
            return sub.all_local, uT, uR
        # the patch's descriptor (:meth:`_descriptor` of the one patch: the same area average, cast)
        f, s = cfg.fovea, cfg.index_side
        q = cv2.resize(patch[: self.P0].reshape(f, f), (s, s), interpolation=cv2.INTER_AREA)
        q = q.astype(np.float32).reshape(1, self.D)
        M = cfg.index_shortlist
        # index: the M nearest descriptors (L2) in one vectorised OpenCV call (no BLAS threads)
        _, nidx = cv2.batchDistance(q, sub.desc, cv2.CV_32F, normType=cv2.NORM_L2SQR, K=M)
        T = nidx.ravel().astype(np.int64)
        T = T[T >= 0]
        if predicted >= 0 and not (T == predicted).any():
            T = np.concatenate((T, np.array([predicted], np.int64)))  # np.append(T, predicted)
        assert sub.sample is not None  # set unless exact_all
        uT = self._drive(patch, sub.idx[T], sub.index_buf)
        uR = self._stats_drive(patch, sub)
        if sub.is_all:  # the rest of the library: the sample's units outside the shortlist
            uR = uR[~np.isin(sub.sample, T)]
        return T, uT, uR

    def _drive_stats(
        self, sub: FlcSubset, T: np.ndarray, uT: np.ndarray, uR: np.ndarray | None
    ) -> tuple[float, float, int]:
        """``(mean, var, N)`` of the drive over the population of ``N`` FLCs (the ``N_std`` rule):
        exact, or the exact shortlist plus a stratified estimate of the rest; with candidates the
        sensory layer is global, so the statistics are those of the library sample."""
        if sub.is_all:
            N = sub.n
            if sub.exact_all:
                mean, var = float(uT.mean()), float(uT.var())
            else:  # exact shortlist + stratified estimate of the rest
                assert uR is not None  # gathered above unless exact_all
                uR = uR.astype(np.float64)
                nR = N - T.size
                mR = float(uR.mean()) if uR.size else 0.0
                m2R = float((uR**2).mean()) if uR.size else 0.0
                mean = (float(uT.sum()) + nR * mR) / N
                m2 = (float((uT.astype(np.float64) ** 2).sum()) + nR * m2R) / N
                var = max(0.0, m2 - mean * mean)
        else:  # candidates: the sensory layer is global, statistics over the library sample
            assert uR is not None  # gathered with the candidates
            N = max(self.n_features, 1)
            mean, var = _mean_var(uR.astype(np.float64))
        return mean, var, N

    # -- persistence -------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to restore an identical memory (arrays are copies)."""
        n, f = self._nf, self._nframes
        return {
            "version": STATE_VERSION,
            "config": self.config.model_dump(mode="json"),
            "patch": self._patch[:n].copy(),
            "desc": self._desc[:n].copy(),
            "pos": self._pos[:n].copy(),
            "frame": self._frame[:n].copy(),
            "w": self._w[:n].copy(),
            "fstart": self._fstart[:f].copy(),
            "fcount": self._fcount[:f].copy(),
            "fsize": self._fsize[:f].copy(),
            "fscale": self._fscale[:f].copy(),
            "rng": self._rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, config: VisualConfig | None, state: dict[str, Any]) -> Self:
        """Restore a memory from :meth:`state_dict`; its future outputs (rng included) are identical."""
        mem = cls(config)
        try:
            if int(state.get("version", -1)) != STATE_VERSION:
                raise InputError(f"visual memory state version {state.get('version')!r} is not {STATE_VERSION}")
            patch = np.asarray(state["patch"], np.uint8)
            n = patch.shape[0]
            f = np.asarray(state["fstart"]).shape[0]
            if patch.ndim != 2 or patch.shape[1] != mem.P:
                raise InputError(
                    f"state patches have shape {patch.shape}, expected (n, {mem.P}) for the configured fovea"
                )
            mem._reserve(n, f)
            mem._patch[:n] = patch
            desc = np.asarray(state["desc"], np.float32)
            if desc.shape != (n, mem.D):
                raise InputError(f"state descriptors have shape {desc.shape}, expected ({n}, {mem.D})")
            mem._desc[:n] = desc
            mem._z[:n] = mem._n[patch].sum(axis=1)
            mem._pos[:n] = np.asarray(state["pos"], np.int32).reshape(n, 2)
            mem._frame[:n] = np.asarray(state["frame"], np.int32).reshape(n)
            mem._w[:n] = np.asarray(state["w"], np.float32).reshape(n)
            mem._fstart[:f] = np.asarray(state["fstart"], np.int64)
            mem._fcount[:f] = np.asarray(state["fcount"], np.int64)
            mem._fsize[:f] = np.asarray(state["fsize"], np.int32).reshape(f, 2)
            # older states lack the input scale of each frame: assume the working size (scale 1)
            mem._fscale[:f] = np.asarray(state.get("fscale", np.ones(f)), np.float32).reshape(f)
            if int(mem._fcount[:f].sum()) != n:
                raise InputError("state frame table does not add up to the stored features")
            mem._nf, mem._nframes = n, f
            mem._rng.bit_generator.state = state["rng"]
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"malformed visual memory state: {exc!r}") from exc
        return mem
