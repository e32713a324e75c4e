"""The feature label cells one recognition may use (:class:`FlcSubset`) and what the subsets of one
library state share (:class:`_Library`).

A recognition restricted to candidate frames drives only their FLCs, and estimates the population's
statistics (the ``N_std`` rule of [BBc]) over the whole library's sensory layer from a fixed stratified
sample. What is fixed for a whole recognition is gathered here once (row indices, the learned patches
shifted into the high byte of the drive table's index, normalisers, buffers) instead of once per
fixation; the drive itself is :class:`~hippomap.feature_store.FeatureStore`'s.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .feature_store import FeatureStore

__all__ = ["FlcSubset"]


class _Library:
    """What every subset of one library state shares (remembered per library size, read only): the
    statistics sample of the ``N_std`` rule over the whole library (all units while it is small, else a
    fixed stratified sample), and lazily the sample's patches shifted into the high byte of the drive
    table's index and its normalisers, over every pixel (``sample_hi``, the exact rows of a small library) and
    over the statistics pixels (``stats_hi``, the sample driven apart). The library only grows (a learned frame
    appends units, stored rows never change), so its size names its state."""

    def __init__(self, mem: FeatureStore):
        cfg = mem.config
        n = mem.n_features
        self.n = n
        self.mem = mem
        #: whether the sample is the whole library (then its rows are those of every unit, in order)
        self.small = n <= cfg.index_shortlist + cfg.stats_sample
        self.sample = (
            np.arange(n, dtype=np.int64)
            if self.small
            else np.unique(np.linspace(0, n - 1, cfg.stats_sample).round().astype(np.int64))
        )
        self.sample.flags.writeable = False
        self._hi: np.ndarray | None = None
        self._z: np.ndarray | None = None
        self._stats: tuple[np.ndarray, np.ndarray] | None = None  # see stats_hi

    @property
    def sample_hi(self) -> np.ndarray:
        """``_patch[sample].astype(uint16) << 8``, gathered on first use (read only)."""
        if self._hi is None:
            self._hi = self.mem._patch[self.sample].astype(np.uint16) << 8
            self._hi.flags.writeable = False
        return self._hi

    @property
    def sample_z(self) -> np.ndarray:
        """``_z[sample]`` (read only)."""
        if self._z is None:
            self._z = self.mem._z[self.sample]
            self._z.flags.writeable = False
        return self._z

    @property
    def stats_hi(self) -> np.ndarray:
        """The sample's patches at the statistics pixels (``stats_stride``), shifted into the high byte of
        the drive table's index, gathered on first use (read only): the sample driven apart from the exactly
        scored units (:meth:`~hippomap.feature_store.FeatureStore._stats_drive`)."""
        return self._stats_rows()[0]

    @property
    def stats_z(self) -> np.ndarray:
        """The sample's normalisers over the statistics pixels (read only)."""
        return self._stats_rows()[1]

    def _stats_rows(self) -> tuple[np.ndarray, np.ndarray]:
        if self._stats is None:
            pix = self.mem._stats_pix
            if pix is None:  # every pixel: the sample's own rows and normalisers
                self._stats = (self.sample_hi, self.sample_z)
            else:
                patches = np.take(self.mem._patch[self.sample], pix, axis=1)
                hi = np.left_shift(patches, 8, dtype=np.uint16)
                z = self.mem._n[patches].sum(axis=1)  # as the units' own normalisers are summed
                hi.flags.writeable = False
                z.flags.writeable = False
                self._stats = (hi, z)
        return self._stats


class FlcSubset:
    """The FLCs a recognition may use (all, or those of the candidate frames)."""

    def __init__(self, mem: FeatureStore, frames: np.ndarray | None):
        n = mem.n_features
        lib = mem._library()
        self._mem = mem
        self._desc: np.ndarray | None = None  # see desc
        if frames is None:
            self.idx = np.arange(n, dtype=np.int64)
        else:
            # the frames' index ranges concatenated in frame order, without a Python loop over the frames:
            # element j of frame i (ranges laid end to end from offset o_i) is start_i + (j - o_i)
            starts = mem._fstart[frames]
            counts = mem._fcount[frames]
            ends = np.cumsum(counts)
            self.idx = (
                np.repeat(starts - ends + counts, counts) + np.arange(int(ends[-1]) if len(ends) else 0)
            ).astype(np.int64)
        self.n = int(self.idx.size)
        self.is_all = frames is None
        cfg = mem.config
        self.exact_all = self.n <= cfg.index_shortlist + cfg.stats_sample
        # the statistics sample: of the units outside the shortlist (local = global indices) for the whole
        # library, of the whole library for candidates (the sensory layer is global: N_std statistics over
        # the library, not the candidates); the same stratified sample either way, remembered per library
        self.sample = None if self.is_all and self.exact_all else lib.sample
        #: whether the statistics sample is driven apart from the exactly scored units, over the statistics
        #: pixels (``stats_stride``): unless the library is small, when the sample is every unit, scored exactly
        self.stats_apart = self.sample is not None and not lib.small
        # the FLCs whose drive is computed exactly at every fixation are fixed for the whole recognition when
        # no index is used: their learned patches (shifted into the high byte of the drive table's index)
        # and normalisers are gathered once here, not once per fixation
        self.rows: np.ndarray | None = None
        self.rows_inv: np.ndarray | None = None  # see _gather_rows
        # drives of the rows and of the statistics sample per fixation point, for this recognition: a saccade
        # lands on a point fixated before (a microsaccade snaps onto the same feature) about one time in eight
        self.drives: dict[tuple[int, int], tuple[np.ndarray, np.ndarray | None]] = {}
        #: local indices of the units scored exactly when no index is used (all of the subset, read only)
        self.all_local = np.arange(self.n)
        self.all_local.flags.writeable = False
        if self.exact_all:
            self._gather_rows(mem, lib)
        else:  # the index's buffer: the shortlist plus the predicted unit
            self.index_buf = np.empty((cfg.index_shortlist + 1, mem.P), np.uint16)
        if self.stats_apart:
            # the statistics sample is the same at every fixation: its patches (high byte of the table index)
            # and normalisers are gathered once per library
            self.stats_hi = lib.stats_hi
            self.stats_z = lib.stats_z
            self.stats_buf = np.empty(self.stats_hi.shape, np.uint16)

    def _gather_rows(self, mem: FeatureStore, lib: _Library) -> None:
        """The rows scored exactly at every fixation when no index is used (the subset; for candidates in a
        small library, then the library's statistics sample, which is every unit), their learned patches
        shifted into the high byte of the drive table's index, their normalisers and the buffer of their
        table indices."""
        if lib.small:
            # a unit both candidate and in the sample is gathered once (a row's drive does not depend on the
            # other rows of the gather): the unique rows are the whole library 0..n-1, each row's position
            # among them is the row itself (rows_inv), and their patches are the library's sample's
            self.rows = rows = self.idx if self.is_all else np.concatenate([self.idx, lib.sample])
            self.rows_inv = rows if self.n and not self.is_all else None
            self.rows_hi = lib.sample_hi
            self.rows_z = lib.sample_z
        else:
            # the subset's own units (whole frames: no unit twice); the sample is driven apart (stats_apart)
            self.rows = self.idx
            self.rows_inv = None
            # = _patch[idx].astype(uint16) << 8: the cast is left_shift's own (one pass less)
            self.rows_hi = np.left_shift(np.take(mem._patch, self.idx, axis=0), 8, dtype=np.uint16)
            self.rows_z = mem._z[self.idx]
        self.rows_buf = np.empty(self.rows_hi.shape, np.uint16)

    @property
    def desc(self) -> np.ndarray:
        """The index descriptors of the subset's units (row ``i`` = local unit ``i``), gathered on first use:
        only the index reads them."""
        if self._desc is None:
            mem = self._mem
            self._desc = mem._desc[: self.n] if self.is_all else mem._desc[self.idx]
        return self._desc

    def local(self, global_index: int) -> int:
        """Index of a global FLC in this subset, or -1 (``idx`` is sorted: frames ascending)."""
        if self.is_all:
            return int(global_index)
        i = int(self.idx.searchsorted(global_index))
        return i if i < self.n and int(self.idx[i]) == int(global_index) else -1
