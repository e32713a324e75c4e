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
  frame hypotheses; the most active frame chooses the next feature; the saccade vector to
  it is decoded from the grid code (Eqs. 4-5, :mod:`hippomap.visual_grid_cells`); a
  microsaccade snaps the fovea to the best match of the predicted patch within
  ``tolerance_px``; the feature found there (or not) updates the evidence; a frame is
  accepted above ``decision_threshold`` (0.9) once it has also predicted
  ``verify_saccades`` further features correctly (optionally more after resets,
  ``verify_per_reset``; [S] §3.2: "it will continue to scan");
  an attempt resets after ``max_prediction_errors`` wrong predictions and the query is
  rejected after ``max_resets`` resets.

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
shortlist plus a fixed stratified sample of ``stats_sample`` other units. With
``candidates`` only the candidate frames' FLCs compete, but the statistics stay those of
the whole library (the sensory layer is global; the candidates gate the frame nodes).

Project choices that differ from [BBc]/spec (each a :class:`~hippomap.config.VisualConfig`
field; measured by ``python bench/bench_visual.py --ablation``): ``max_survivors`` 5,
``tolerance_px`` 8, ``next_target="nearest"``, ``prediction_tolerance`` 0.9,
``start_order="strongest"``, ``verify_saccades`` 2, ``anchor="start"``, the retina front
end (``retina_*``) with ``n_std`` 3.3; plus the FLC index (``index_*``, ``stats_sample``)
for scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Literal, cast

import cv2
import numpy as np

from .config import VisualConfig
from .errors import InputError
from .retina import Retina
from .retina import imadjust as _imadjust  # noqa: F401  (kept importable from here)
from .visual_grid_cells import SpatialViewCells, VisualGridCells

__all__ = [
    "VisualMemory",
    "Recognition",
    "shift_summary",
    "SaccadeStep",
    "prepare_image",
    "prepare_views",
    "draw_trace",
    "draw_frame_features",
]

STATE_VERSION = 1


def _lut16_works() -> bool:
    """Whether this OpenCV's ``LUT`` takes a 65,536-entry table indexed by uint16 (OpenCV >= 5)."""
    try:
        out = cv2.LUT(np.array([[0, 65535]], np.uint16), np.arange(65536, dtype=np.float32).reshape(1, -1))
    except cv2.error:
        return False
    return out.dtype == np.float32 and out.tolist() == [[0.0, 65535.0]]


_LUT16 = _lut16_works()
_DECODE_CACHE = 1 << 15  # decoded saccade vectors remembered per memory (a few MB at most)


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


# ---------------------------------------------------------------------------------------
# input images
# ---------------------------------------------------------------------------------------
def _check_image(image: Any, name: str = "image") -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name} must be a numpy array (H x W gray or H x W x 3 BGR, uint8), got {type(image).__name__}")
    if image.size == 0:
        raise InputError(f"{name} is empty (shape {image.shape})")
    if image.dtype != np.uint8:
        raise InputError(f"{name} must have dtype uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise InputError(f"{name} must be H x W or H x W x 3/4, got shape {image.shape}")


def prepare_image(image: Any, config: VisualConfig | None = None, name: str = "image") -> tuple[np.ndarray, float]:
    """Validate and convert a frame to the memory's working image (what the sensory cells see).

    Gray (BGR/BGRA converted), resized to ``working_width`` (aspect kept), then passed
    through the :class:`~hippomap.retina.Retina` (``retina_mode="none"``: contrast
    stretched like ``imadjust``, spec §2 learning step 1). Returns ``(work, scale)`` where
    ``scale`` = original px per working px. Raises :class:`InputError` for non-arrays,
    empty images, dtypes other than uint8, bad shapes and images too small for the fovea.
    """
    gray, work, scale = prepare_views(image, config, name)
    return work, scale


def _working_size(image: Any, cfg: VisualConfig, name: str = "image") -> tuple[np.ndarray, int, int]:
    """``(gray, width, height)``: the frame as grey levels and its size at the working width, or
    :class:`InputError` for anything the memory could not learn or recognise (no image work
    beyond the grey conversion: what every frame must pass, key frame or not)."""
    gray = _check_image(image, name)
    h0, w0 = gray.shape
    if min(h0, w0) < cfg.fovea:
        raise InputError(f"{name} of {w0}x{h0} px is too small for the {cfg.fovea}-px fovea")
    width = cfg.working_width
    height = max(1, int(round(h0 * width / w0)))
    need = 2 * cfg.fovea + 2
    if height < need:
        raise InputError(
            f"{name} of {w0}x{h0} px becomes {width}x{height} at the working width; the {cfg.fovea}-px fovea needs "
            f"at least {need} px on each side"
        )
    return gray, width, height


def prepare_views(image: Any, config: VisualConfig | None = None,
                  name: str = "image") -> tuple[np.ndarray, np.ndarray, float]:
    """Like :func:`prepare_image`, also returning the working-size grey image before the retina:
    ``(gray, work, scale)``; fixation points are chosen on ``gray`` or ``work`` (``corner_source``).
    ``work`` is ``H x W`` (the ganglion image), or ``H x W x (1 + v1_orientations)`` with the V1
    orientation channels behind it (:meth:`~hippomap.retina.Retina.sensory_image`)."""
    cfg = config or VisualConfig()
    gray, width, height = _working_size(image, cfg, name)
    h0, w0 = gray.shape
    interp = cv2.INTER_AREA if width < w0 else cv2.INTER_LINEAR
    work = cv2.resize(gray, (width, height), interpolation=interp) if (width, height) != (w0, h0) else gray.copy()
    return work, Retina(cfg).sensory_image(work), w0 / float(width)


# ---------------------------------------------------------------------------------------
# result objects
# ---------------------------------------------------------------------------------------
def _pt(p: Any) -> list[float] | None:
    return None if p is None else [float(p[0]), float(p[1])]


def shift_summary(correspondences: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Robust image shift of correspondences ``{"query": [x, y], "memory": [x, y]}``:
    ``{"x", "y"}`` = median of query - memory, ``{"mad_x", "mad_y"}`` = median absolute
    deviation from it, ``n`` = count; ``None`` for no correspondences."""
    if not correspondences:
        return None
    d = np.array([[c["query"][0] - c["memory"][0], c["query"][1] - c["memory"][1]] for c in correspondences], float)
    med = np.median(d, axis=0)
    mad = np.median(np.abs(d - med), axis=0)
    return {"x": float(med[0]), "y": float(med[1]), "mad_x": float(mad[0]), "mad_y": float(mad[1]),
            "n": int(len(d))}


@dataclass
class SaccadeStep:
    """One fixation of a recognition: where the fovea was, what was predicted, what was found.

    Points are (x, y) = (col, row) in the coordinates of the *input* image.
    ``outcome``: ``"start"`` first fixation of an attempt with evidence, ``"confirmed"``
    the predicted feature won, ``"mismatch"`` another feature won, ``"no_evidence"`` no
    feature unit passed the ``N_std`` test. ``event``: what followed — ``None``,
    ``"accept"``, or ``"reset: <reason>"``.
    """

    attempt: int
    fixation: tuple[float, float]
    target: tuple[float, float] | None
    predicted_frame: int | None
    predicted_feature: int | None
    found_frame: int | None
    found_feature: int | None
    similarity: float
    outcome: str
    evidence: list[tuple[int, float]]
    event: str | None = None

    def to_dict(self) -> dict[str, Any]:
        # what dataclasses.asdict gives (same keys, same order), without its recursive deep copy: every
        # field is a scalar, a string or None apart from the three converted here
        return {
            "attempt": self.attempt,
            "fixation": _pt(self.fixation),
            "target": _pt(self.target),
            "predicted_frame": self.predicted_frame,
            "predicted_feature": self.predicted_feature,
            "found_frame": self.found_frame,
            "found_feature": self.found_feature,
            "similarity": self.similarity,
            "outcome": self.outcome,
            "evidence": [[int(f), float(a)] for f, a in self.evidence],
            "event": self.event,
        }


@dataclass
class Recognition:
    """The outcome of :meth:`VisualMemory.recognise`.

    ``frame_id``: the accepted frame, or ``None`` (rejected). ``steps``: every fixation in
    order, each with the evidence of the leading hypotheses after it (``evidence``).
    ``confidence`` in [0, 1]: the fraction of confirmed predictions in the accepting
    attempt, discounted by the resets needed (0 when rejected); used for PR curves.

    ``correspondences`` (accepted only): for the start fixation and every confirmed
    fixation of the accepting attempt whose feature belongs to the accepted frame,
    ``{"query": [x, y], "memory": [x, y], "feature": k, "outcome": ...}`` — the fixation on
    the query and the matched feature's position in the learned frame, both in input-image
    px. ``shift``: their robust summary (:func:`shift_summary`): ``x``, ``y`` = median of
    query - memory, ``mad_x``, ``mad_y`` = median absolute deviations, ``n`` = count; ``None``
    without correspondences. A positive ``x`` means the scene appears further right in
    the query than when it was learned.
    """

    frame_id: int | None
    evidence: float
    steps: list[SaccadeStep] = field(default_factory=list)
    n_resets: int = 0
    confidence: float = 0.0
    image_size: tuple[int, int] = (0, 0)
    reason: str = ""
    correspondences: list[dict[str, Any]] = field(default_factory=list)
    shift: dict[str, Any] | None = None

    @property
    def accepted(self) -> bool:
        return self.frame_id is not None

    @property
    def frame(self) -> int | None:
        """Alias of :attr:`frame_id` (used by :mod:`hippomap.mapper`)."""
        return self.frame_id

    @property
    def n_fixations(self) -> int:
        return len(self.steps)

    @property
    def trace(self) -> list[tuple[float, float]]:
        """Fixation points (x, y) in input-image coordinates, one per step."""
        return [s.fixation for s in self.steps]

    @property
    def evidence_trace(self) -> list[list[tuple[int, float]]]:
        """Leading hypotheses (frame, activity) after each step."""
        return [s.evidence for s in self.steps]

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Recognition":
        """Rebuild a recognition from :meth:`to_dict` (e.g. to draw a stored trace)."""
        try:
            steps = [
                SaccadeStep(
                    attempt=int(s["attempt"]), fixation=tuple(s["fixation"]),
                    target=None if s.get("target") is None else tuple(s["target"]),
                    predicted_frame=s.get("predicted_frame"), predicted_feature=s.get("predicted_feature"),
                    found_frame=s.get("found_frame"), found_feature=s.get("found_feature"),
                    similarity=float(s.get("similarity", 0.0)), outcome=str(s["outcome"]),
                    evidence=[(int(f), float(a)) for f, a in s.get("evidence", [])], event=s.get("event"),
                )
                for s in d.get("steps", [])
            ]
            return cls(
                frame_id=None if d.get("frame_id") is None else int(d["frame_id"]),
                evidence=float(d.get("evidence") or 0.0), steps=steps, n_resets=int(d.get("n_resets", 0)),
                confidence=float(d.get("confidence") or 0.0), image_size=tuple(d.get("image_size", (0, 0))),
                reason=str(d.get("reason", "")),
                correspondences=[
                    {"query": [float(c["query"][0]), float(c["query"][1])],
                     "memory": [float(c["memory"][0]), float(c["memory"][1])],
                     "feature": int(c.get("feature", -1)), "outcome": str(c.get("outcome", ""))}
                    for c in d.get("correspondences") or []
                ],
                shift=None if not d.get("shift") else {str(k): (int(v) if k == "n" else float(v))
                                                       for k, v in d["shift"].items()},
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed recognition dict: {exc!r}") from exc

    def to_dict(self) -> dict[str, Any]:
        return {
            "frame_id": None if self.frame_id is None else int(self.frame_id),
            "accepted": self.accepted,
            "evidence": float(self.evidence),
            "confidence": float(self.confidence),
            "n_resets": int(self.n_resets),
            "n_fixations": self.n_fixations,
            "image_size": [int(self.image_size[0]), int(self.image_size[1])],
            "reason": self.reason,
            "steps": [s.to_dict() for s in self.steps],
            "correspondences": [
                {"query": [float(c["query"][0]), float(c["query"][1])],
                 "memory": [float(c["memory"][0]), float(c["memory"][1])],
                 "feature": int(c["feature"]), "outcome": str(c["outcome"])} for c in self.correspondences
            ],
            "shift": None if self.shift is None else {k: (int(v) if k == "n" else float(v))
                                                      for k, v in self.shift.items()},
        }


# ---------------------------------------------------------------------------------------
# the memory
# ---------------------------------------------------------------------------------------
@dataclass
class _Sense:
    """What the FLC population reports at one fixation (local indices into the subset)."""

    evidence: bool
    winner: int  # local index of argmax u (valid even without evidence)
    umax: float
    survivors: np.ndarray | None = None  # local indices
    weights: np.ndarray | None = None  # softmax weights of the survivors
    top: int = -1  # argmax of the biased, pruned vector (local)
    upred: float = 0.0  # drive of the predicted unit


class _Subset:
    """The FLCs a recognition may use (all, or those of the candidate frames)."""

    def __init__(self, mem: "VisualMemory", frames: np.ndarray | None):
        n = mem.n_features
        if frames is None:
            self.idx = np.arange(n, dtype=np.int64)
            self.desc = mem._desc[:n]
        else:
            starts = mem._fstart[frames]
            counts = mem._fcount[frames]
            self.idx = (
                np.concatenate([np.arange(s, s + c) for s, c in zip(starts, counts)]).astype(np.int64)
                if len(frames)
                else np.zeros(0, np.int64)
            )
            self.desc = mem._desc[self.idx]
        self.n = int(self.idx.size)
        self.is_all = frames is None
        cfg = mem.config
        self.exact_all = self.n <= cfg.index_shortlist + cfg.stats_sample
        if self.is_all:
            # stratified sample of the units outside the shortlist (local = global indices)
            self.sample = None if self.exact_all else np.unique(
                np.linspace(0, self.n - 1, cfg.stats_sample).round().astype(np.int64))
        else:
            # the sensory layer is global: N_std statistics over the whole library, not the candidates
            n_all = mem.n_features
            self.sample = (np.arange(n_all, dtype=np.int64) if n_all <= cfg.index_shortlist + cfg.stats_sample
                           else np.unique(np.linspace(0, n_all - 1, cfg.stats_sample).round().astype(np.int64)))
        # the FLCs whose drive is computed exactly at every fixation are fixed for the whole recognition when
        # no index is used: their learned patches (shifted into the high byte of the drive table's index)
        # and normalisers are gathered once here, not once per fixation
        self.rows: np.ndarray | None = None
        # drives of the rows per fixation point, for this recognition: a saccade lands on a point
        # fixated before (a microsaccade snaps onto the same feature) about one time in eight
        self.drives: dict[tuple[int, int], np.ndarray] = {}
        if self.exact_all:
            self.rows = self.idx if self.is_all else np.concatenate([self.idx, self.sample])
            self.rows_hi = mem._patch[self.rows].astype(np.uint16) << 8
            self.rows_z = mem._z[self.rows]
            self.rows_buf = np.empty_like(self.rows_hi)

    def local(self, global_index: int) -> int:
        """Index of a global FLC in this subset, or -1 (``idx`` is sorted: frames ascending)."""
        if self.is_all:
            return int(global_index)
        i = int(np.searchsorted(self.idx, global_index))
        return i if i < self.n and int(self.idx[i]) == int(global_index) else -1


class VisualMemory:
    """Library of key frames learned one-shot, recognised by saccade sequences (paper §2.2).

    >>> mem = VisualMemory()                      # doctest: +SKIP
    >>> fid = mem.learn(frame)                    # int, or None if the frame has < min_fixations corners
    >>> rec = mem.recognise(other_frame)          # Recognition; rec.frame_id is None if rejected
    >>> rec = mem.recognise(other_frame, candidates=[3, 4, 9])
    """

    def __init__(self, config: VisualConfig | None = None):
        self.config = cfg = config or VisualConfig()
        if cfg.fovea % 2 == 0:
            raise InputError(f"fovea must be odd (2h+1), got {cfg.fovea}")
        self.grid = VisualGridCells(cfg)
        self.h = cfg.fovea // 2
        # a feature unit's sensory field: the fovea of the ganglion image, then the fovea of each
        # orientation channel sampled every v1_stride px (prepare_views stacks them in this order)
        self.P0 = cfg.fovea * cfg.fovea
        self._n_ori = cfg.v1_orientations if cfg.retina_mode != "none" else 0
        self._ori_side = len(range(0, cfg.fovea, cfg.v1_stride))
        self.P = self.P0 + self._n_ori * self._ori_side**2
        self.D = cfg.index_side * cfg.index_side
        # sensory cells: s_a(v) = exp(-((a - v)/sigma)^2), cut below the cutoff ([BBc])
        v = np.arange(256, dtype=np.float64)
        S = np.exp(-(((v[:, None] - v[None, :]) / cfg.sensory_sigma) ** 2))
        S[S < cfg.sensory_cutoff] = 0.0
        self._K = (S @ S.T).astype(np.float32).ravel()  # K[a, b] flattened, a = learned, b = seen
        self._n = S.sum(axis=1).astype(np.float32)  # sum_v s_a(v)
        self._rng = np.random.default_rng(cfg.seed)
        self._svc: SpatialViewCells | None = None
        self._decoded: dict[bytes, np.ndarray] = {}  # see _decode
        self._last_views: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None  # see _views
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
        _working_size(image, self.config, name)

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

    # -- helpers ------------------------------------------------------------------------
    @property
    def spatial_view_cells(self) -> SpatialViewCells:
        """Spatial view cells over the working view plane (built on first use)."""
        if self._svc is None:
            cfg = self.config
            self._svc = SpatialViewCells(self.grid, cfg.working_width, cfg.working_width, cfg.svc_stride)
        return self._svc

    def _decode(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Saccade vector from gaze ``m`` to ``target`` decoded from their grid codes (a fresh array).

        Both points are whole pixels during a recognition (learned positions, fovea positions), and
        the decoded vector is a fixed function of the two points, so it is remembered per pair: the
        same candidate frames come back recognition after recognition with the same feature pairs."""
        m, target = np.asarray(m, dtype=float), np.asarray(target, dtype=float)
        key = m.tobytes() + target.tobytes()  # bytes, so that even -0.0 and 0.0 stay apart
        d = self._decoded.get(key)
        if d is None:
            if len(self._decoded) >= _DECODE_CACHE:
                self._decoded.clear()
            d = self._decode_uncached(m, target)
            d.flags.writeable = False
            self._decoded[key] = d
        return d.copy()

    def _decode_uncached(self, m: np.ndarray, target: np.ndarray) -> np.ndarray:
        g_cur = self.grid.encode(m)
        g_tgt = self.grid.encode(target)  # = W_FLC->GC e_k*
        if self.config.decoder == "svc":
            return self.spatial_view_cells.decode(g_cur, g_tgt)
        return self.grid.decode(g_cur, g_tgt)

    def _views(self, image: Any) -> tuple[np.ndarray, float, np.ndarray]:
        """``(work, scale, corner image)`` of a frame: :func:`prepare_views`, then the image whose corners
        become fixation points (``corner_source``).

        The mapper recognises a key frame and then learns the same frame: the views of the last frame
        are kept with a copy of it, and a frame equal to it (same shape, dtype and pixels) gets them
        again instead of another pass through the retina. The kept arrays are read-only."""
        cfg = self.config
        last = self._last_views
        if (last is not None and isinstance(image, np.ndarray) and image.shape == last[0].shape
                and image.dtype == last[0].dtype and np.array_equal(image, last[0])):
            return last[1], last[2], last[3]
        gray, work, scale = prepare_views(image, cfg)
        cimg = _channel0(work) if cfg.corner_source == "retina" else _imadjust(gray, cfg.contrast_clip)
        for a in (work, cimg):
            a.flags.writeable = False
        self._last_views = (np.array(image, copy=True), work, scale, cimg)
        return work, scale, cimg

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
        m = self._margin()
        H, W = img.shape
        mask = np.zeros_like(img)
        mask[m : H - m, m : W - m] = 255
        pts = cv2.goodFeaturesToTrack(
            img, maxCorners=int(k), qualityLevel=self.config.corner_quality, minDistance=float(min_dist),
            mask=mask, blockSize=self.config.corner_block,
        )
        if pts is None:
            return np.zeros((0, 2), np.int32)
        return np.rint(pts.reshape(-1, 2)).astype(np.int32)

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
        return np.stack([self._patch_at(img, int(x), int(y)) for x, y in pts]) if len(pts) else np.zeros(
            (0, self.P), np.uint8
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

    # -- sensing -----------------------------------------------------------------------
    def _drive(self, patch: np.ndarray, flc: np.ndarray) -> np.ndarray:
        """Exact FLC drive u_k of a fovea patch (uint8, P) for global FLC indices ``flc``."""
        if flc.size == 0:
            return np.zeros(0, np.float32)
        # flat index a * 256 + b into K, built in uint16 (fast gather; 255 * 256 + 255 fits)
        idx = (self._patch[flc].astype(np.uint16) << 8) | patch[None, :]
        return _gather_k(self._K, idx).sum(axis=1) / self._z[flc]

    def _drive_rows(self, patch: np.ndarray, sub: _Subset) -> np.ndarray:
        """:meth:`_drive` of ``sub.rows`` from the subset's gathered patches (same numbers, no row gather)."""
        if sub.rows is None or sub.rows.size == 0:
            return np.zeros(0, np.float32)
        idx = np.bitwise_or(sub.rows_hi, patch[None, :], out=sub.rows_buf)
        return _gather_k(self._K, idx).sum(axis=1) / sub.rows_z

    def _sense(self, img: np.ndarray, pos: np.ndarray, sub: _Subset, predicted: int) -> _Sense:
        """Drive of the FLC population at fixation ``pos`` and the [BBc] pruning: evidence test
        ``max u > mean + N_std sd``, ``u / max u``, bias on the predicted unit, prune, softmax."""
        cfg = self.config
        x, y = int(pos[0]), int(pos[1])
        patch = self._patch_at(img, x, y)
        uR = None
        if sub.exact_all:
            T = np.arange(sub.n)
            # the drive of the same rows at the same point of the same image: remembered (read only)
            u = sub.drives.get((x, y))
            if u is None:
                u = self._drive_rows(patch, sub)
                u.flags.writeable = False
                sub.drives[(x, y)] = u
            if sub.is_all:
                uT = u
            else:  # candidates and the library sample of the statistics in one gather
                uT, uR = u[: sub.n], u[sub.n :]
        else:
            q = self._descriptor(patch[None, :])
            M = cfg.index_shortlist
            # index: the M nearest descriptors (L2) in one vectorised OpenCV call (no BLAS threads)
            _, nidx = cv2.batchDistance(q, sub.desc, cv2.CV_32F, normType=cv2.NORM_L2SQR, K=M)
            T = nidx.ravel().astype(np.int64)
            T = T[T >= 0]
            if predicted >= 0 and not np.any(T == predicted):
                T = np.append(T, predicted)
            # shortlist and statistics sample in one gather
            assert sub.sample is not None  # set unless exact_all
            extra = np.setdiff1d(sub.sample, T) if sub.is_all else sub.sample
            u = self._drive(patch, np.concatenate([sub.idx[T], extra]))
            uT, uR = u[: T.size], u[T.size :]
        # population statistics of the drive (mean, var) for the N_std rule
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
            uL = uR.astype(np.float64)
            N = max(self.n_features, 1)
            mean, var = float(uL.mean()), float(uL.var())
        j = int(np.argmax(uT))
        umax = float(uT[j])
        winner = int(T[j])
        upred = 0.0
        if predicted >= 0:
            pk = np.flatnonzero(T == predicted)
            upred = float(uT[pk[0]]) if pk.size else 0.0
        if not umax > mean + cfg.n_std * math.sqrt(var) or umax <= 0:
            return _Sense(False, winner, umax, upred=upred)
        # normalise, bias the predicted unit, prune at mean + N_std sd, softmax ([BBc])
        ut = uT / umax
        mean_t, var_t = mean / umax, var / umax**2
        if predicted >= 0:
            pk = np.flatnonzero(T == predicted)
            if pk.size:
                p = int(pk[0])
                old = float(ut[p])
                ut = ut.copy()
                ut[p] = old * cfg.prediction_bias
                m2_t = var_t + mean_t**2 + (ut[p] ** 2 - old**2) / N
                mean_t = mean_t + (ut[p] - old) / N
                var_t = max(0.0, m2_t - mean_t**2)
        keep = ut >= mean_t + cfg.n_std * math.sqrt(var_t)
        if not np.any(keep):
            keep[int(np.argmax(ut))] = True
        if cfg.max_survivors and int(keep.sum()) > cfg.max_survivors:
            # spec §6.4: N_std must grow with the library so that 1-5 FLCs survive; a top-K cap
            # does that for every library size
            idx = np.flatnonzero(keep)
            top = idx[np.argsort(-ut[idx], kind="stable")[: cfg.max_survivors]]
            keep = np.zeros_like(keep)
            keep[top] = True
        surv = T[keep]
        vals = ut[keep].astype(np.float64) * cfg.softmax_gain
        e = np.exp(vals - vals.max())
        wts = e / e.sum()
        best = int(surv[int(np.argmax(vals))])
        return _Sense(True, winner, umax, surv, wts, best, upred)

    def _microsaccade(self, img: np.ndarray, target: np.ndarray, flc: int) -> np.ndarray | None:
        """Snap the landing point to the best match of the predicted feature within ``tolerance_px``
        (the [BBc] microsaccade); ``None`` if the fovea cannot be placed inside the image."""
        h, r = self.h, self.config.tolerance_px
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
        region = img[y0 - h : y1 + h + 1, x0 - h : x1 + h + 1]
        tmpl = self._patch[flc, : self.P0].reshape(self.config.fovea, self.config.fovea)
        res = cv2.matchTemplate(region, tmpl, cv2.TM_SQDIFF)
        _, _, loc, _ = cv2.minMaxLoc(res)
        return np.array([x0 + loc[0], y0 + loc[1]])

    # -- recognition -------------------------------------------------------------------
    def recognise(self, image: Any, candidates: Iterable[int] | None = None) -> Recognition:
        """Recognise a frame by a saccade sequence (spec §2 recognition; [BBc] main loop).

        ``candidates``: restrict the hypotheses to these frame ids (the cognitive map passes
        the frames of nodes near the current place code); ``None`` = all frames.
        """
        cfg = self.config
        work, scale, cimg = self._views(image)
        H, W = work.shape[:2]
        size = (int(round(W * scale)), int(round(H * scale)))
        if candidates is None:
            frames = None
        else:
            frames = np.unique(np.array([self._check_frame(c) for c in candidates], dtype=np.int64))
        sub = _Subset(self, frames)
        if sub.n == 0:
            return Recognition(None, 0.0, [], 0, 0.0, size, "no stored frames")
        sense_img = self._blur(work) if cfg.query_blur else work
        starts = self._corners(cimg, cfg.query_keypoints, self.h)
        if len(starts) == 0:
            return Recognition(None, 0.0, [], 0, 0.0, size, "no keypoints in the query")
        rng = self._rng
        frame_of = self._frame
        wts = self._w
        a = np.zeros(self._nframes, np.float64)
        steps: list[SaccadeStep] = []
        used_starts: set[int] = set()
        resets = 0

        def to_img(p: np.ndarray | None) -> tuple[float, float] | None:
            return None if p is None else (float(p[0]) * scale, float(p[1]) * scale)

        def leading() -> list[tuple[int, float]]:
            nz = np.flatnonzero(a > 0)
            if nz.size == 0:
                return []
            top = nz[np.argsort(-a[nz], kind="stable")[: cfg.trace_hypotheses]]
            return [(int(f), float(a[f])) for f in top]

        while True:
            # ---- start a new attempt ----------------------------------------------------
            a[:] = 0.0
            pred_err = 0
            visited: list[int] = []
            free = [i for i in range(len(starts)) if i not in used_starts]
            if not free:
                used_starts.clear()
                free = list(range(len(starts)))
            si = int(free[int(rng.integers(len(free)))]) if cfg.start_order == "random" else int(min(free))
            used_starts.add(si)
            e = starts[si].astype(np.int64)  # eye position on the query (working px)
            m = e.copy()  # grid-cell position on the view plane (memory coordinates)
            predicted = -1  # global FLC index predicted at this fixation
            target: np.ndarray | None = None
            n_sacc = 0
            confirmed = 0
            verify_left = -1  # saccades left to verify a hypothesis past the threshold (-1: not verifying)
            accepted_frame = -1
            reset_reason = None
            first = True
            while True:
                s = self._sense(sense_img, e, sub, sub.local(predicted) if predicted >= 0 else -1)
                pf = int(frame_of[predicted]) if predicted >= 0 else None
                if not s.evidence:
                    outcome = "no_evidence"
                    found = None
                    if first:
                        reset_reason = "first fixation not informative"
                else:
                    found = int(sub.idx[s.winner])
                    if first:
                        outcome = "start"
                    elif found == predicted or (predicted >= 0 and s.upred >= cfg.prediction_tolerance * s.umax):
                        outcome = "confirmed"
                        confirmed += 1
                    else:
                        outcome = "mismatch"
                        pred_err += 1
                        if pred_err > cfg.max_prediction_errors:
                            reset_reason = "too many wrong predictions"
                    if reset_reason is None and (outcome != "mismatch" or cfg.update_on_mismatch):
                        assert s.weights is not None  # a fixation with evidence has its survivors' weights
                        g = sub.idx[s.survivors]
                        np.add.at(a, frame_of[g], cfg.kappa * wts[g] * s.weights)
                        np.clip(a, 0.0, 1.0, out=a)
                        if a.sum() > cfg.max_total_activity:
                            reset_reason = "total frame activity too high"
                        if first and cfg.anchor == "start":
                            m = self._pos[found].astype(np.int64)  # global remapping onto the feature
                steps.append(
                    SaccadeStep(
                        attempt=resets, fixation=cast("tuple[float, float]", to_img(e)), target=to_img(target), predicted_frame=pf,
                        predicted_feature=None if predicted < 0 else int(predicted), found_frame=None if found is None
                        else int(frame_of[found]), found_feature=found, similarity=float(s.umax), outcome=outcome,
                        evidence=leading(),
                    )
                )
                first = False
                if reset_reason is None and verify_left > 0:
                    if outcome == "confirmed":  # the accepted frame predicted this feature
                        verify_left -= 1
                    else:
                        reset_reason = "verification saccade failed"
                if reset_reason is None and verify_left < 0 and a.max() > cfg.decision_threshold:
                    accepted_frame = int(np.argmax(a))
                    # every reset is another chance for a wrong frame: later attempts must verify more
                    verify_left = cfg.verify_saccades + int(resets * cfg.verify_per_reset)
                    if verify_left > 0:
                        steps[-1].event = "threshold"
                if reset_reason is None and verify_left == 0:
                    fid = accepted_frame
                    steps[-1].event = "accept"
                    n_att = sum(1 for st in steps if st.attempt == resets)
                    conf = (confirmed + 1) / max(1, n_att) / (1.0 + resets)
                    corr, shift = self._correspondences(steps, resets, fid)
                    return Recognition(fid, float(a[fid]), steps, resets, float(conf), size, "accepted", corr, shift)
                # ---- choose the next target (the most active frame chooses) ---------------
                if reset_reason is None:
                    cur = int(sub.idx[s.top]) if s.evidence else predicted
                    if cur >= 0:
                        if len(visited) >= cfg.n_fixations - 1:
                            visited = [visited[-1], cur]
                        else:
                            visited.append(cur)
                    if n_sacc >= cfg.max_saccades:
                        reset_reason = "saccade cap reached"
                if reset_reason is None:
                    k_star, tgt, land, why = self._choose_target(a, e, m, visited, rng, sense_img,
                                                                 accepted_frame if verify_left > 0 else -1)
                    if k_star < 0:
                        reset_reason = why
                    else:
                        n_sacc += 1
                        target = tgt
                        e = land.astype(np.int64)
                        m = self._pos[k_star].astype(np.int64) if cfg.anchor == "start" else e.copy()
                        predicted = k_star
                        continue
                # ---- reset ------------------------------------------------------------------
                steps[-1].event = f"reset: {reset_reason}"
                resets += 1
                if resets > cfg.max_resets:
                    return Recognition(None, float(a.max()) if a.size else 0.0, steps, resets - 1, 0.0, size,
                                       f"no match after {cfg.max_resets} resets")
                break

    def _correspondences(self, steps: list[SaccadeStep], attempt: int,
                         fid: int) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
        """Image correspondences of the accepting attempt and their robust shift summary.

        One per fixation of ``attempt`` whose feature belongs to the accepted frame ``fid``:
        the start fixation with the feature that won it, every confirmed fixation with the
        predicted feature (the microsaccade has snapped the fovea onto it). ``query`` is the
        fixation, ``memory`` the feature's learned position, both in input-image px."""
        corr: list[dict[str, Any]] = []
        for st in steps:
            if st.attempt != attempt:
                continue
            if st.outcome == "start":
                k = st.found_feature
            elif st.outcome == "confirmed":
                k = st.predicted_feature
            else:
                continue
            if k is None or int(self._frame[k]) != fid:
                continue
            sc = float(self._fscale[fid])
            mx, my = (float(v) * sc for v in self._pos[k])
            corr.append({"query": [float(st.fixation[0]), float(st.fixation[1])], "memory": [mx, my],
                         "feature": int(k), "outcome": st.outcome})
        return corr, shift_summary(corr)

    def _choose_target(self, a: np.ndarray, e: np.ndarray, m: np.ndarray, visited: list[int],
                       rng: np.random.Generator, img: np.ndarray, frame: int = -1) -> tuple[int, Any, Any, str]:
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
        ks = np.concatenate([np.arange(self._fstart[f], self._fstart[f] + self._fcount[f]) for f in active])
        if cfg.next_target == "stochastic":
            v = self._w[ks] * a[self._frame[ks]] * (1.0 - rng.random(ks.size))  # (1 - U) W_ID->FLC a ([BBc])
        elif cfg.next_target == "most_active":
            v = 0.5 + 0.5 * rng.random(ks.size)  # a random unvisited feature of the leading frame ([S])
        else:  # "nearest": the leading frame's unvisited feature closest to the gaze (short saccades)
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
        for j in order:  # best first; usually the first candidate is taken
            k = int(ks[j])
            d = self._decode(mf, self._pos[k].astype(float)).astype(np.int64)  # decode(g(m), W_FLC->GC e_k)
            if abs(int(d[0])) <= tol and abs(int(d[1])) <= tol:
                continue  # [BBc]: choose again while the vector is within tolerance
            tgt = e + d
            land = self._microsaccade(img, tgt, k)
            if land is None:
                if cfg.out_of_view == "skip":
                    continue  # the predicted feature lies outside this view: look at another one
                return -1, None, None, "saccade out of the image"
            return k, tgt, land, ""
        return -1, None, None, "no feature left to predict"

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
    def from_state(cls, config: VisualConfig | None, state: dict[str, Any]) -> "VisualMemory":
        """Restore a memory from :meth:`state_dict`; its future outputs (rng included) are identical."""
        mem = cls(config)
        try:
            if int(state.get("version", -1)) != STATE_VERSION:
                raise InputError(f"visual memory state version {state.get('version')!r} is not {STATE_VERSION}")
            patch = np.asarray(state["patch"], np.uint8)
            n = patch.shape[0]
            f = np.asarray(state["fstart"]).shape[0]
            if patch.ndim != 2 or patch.shape[1] != mem.P:
                raise InputError(f"state patches have shape {patch.shape}, expected (n, {mem.P}) for the configured fovea")
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


# ---------------------------------------------------------------------------------------
# drawing (for the viewer and the evaluation's example images)
# ---------------------------------------------------------------------------------------
_COLORS = {
    "start": (255, 160, 0),
    "confirmed": (0, 200, 0),
    "mismatch": (0, 0, 255),
    "no_evidence": (160, 160, 160),
}


def _to_bgr(image: Any) -> np.ndarray:
    gray_or_bgr = image
    if not isinstance(gray_or_bgr, np.ndarray) or gray_or_bgr.size == 0 or gray_or_bgr.dtype != np.uint8:
        raise InputError("draw_trace needs a non-empty uint8 image")
    if gray_or_bgr.ndim == 2:
        return cv2.cvtColor(gray_or_bgr, cv2.COLOR_GRAY2BGR)
    if gray_or_bgr.ndim == 3 and gray_or_bgr.shape[2] == 3:
        return gray_or_bgr.copy()
    if gray_or_bgr.ndim == 3 and gray_or_bgr.shape[2] == 4:
        return cv2.cvtColor(gray_or_bgr, cv2.COLOR_BGRA2BGR)
    raise InputError(f"draw_trace: bad image shape {gray_or_bgr.shape}")


def draw_trace(image: Any, recognition: Recognition, attempt: int | Literal["last", "all"] = "last",
               fovea: int | None = None, scale: float = 1.0) -> np.ndarray:
    """Draw a recognition's saccade trace on the query frame -> BGR uint8 image.

    Numbered fixations (blue = start, green = predicted feature found, red = another
    feature found, gray = no evidence), the saccade lines between them, and for every
    saccade the predicted landing point (yellow cross) where it differs from the fixation
    after the microsaccade. ``fovea``: draw the fovea square (input-image px) at each fixation.
    ``scale``: enlarge the drawing (e.g. 3 for a 160 x 120 frame).
    """
    canvas = _scaled(_to_bgr(image), scale)
    H, W = canvas.shape[:2]
    s = max(1.0, W / 320.0)
    steps = recognition.steps
    if attempt == "last":
        last = steps[-1].attempt if steps else 0
        steps = [st for st in steps if st.attempt == last]
    elif attempt != "all":
        steps = [st for st in steps if st.attempt == int(attempt)]
    prev = None
    prev_attempt = None
    for i, st in enumerate(steps, 1):
        p = (int(round(st.fixation[0] * scale)), int(round(st.fixation[1] * scale)))
        if prev is not None and prev_attempt == st.attempt:
            cv2.line(canvas, prev, p, (0, 0, 230), max(1, int(s)), cv2.LINE_AA)
        if st.target is not None:
            t = (int(round(st.target[0] * scale)), int(round(st.target[1] * scale)))
            if t != p:
                d = int(4 * s)
                cv2.line(canvas, (t[0] - d, t[1] - d), (t[0] + d, t[1] + d), (0, 230, 230), 1, cv2.LINE_AA)
                cv2.line(canvas, (t[0] - d, t[1] + d), (t[0] + d, t[1] - d), (0, 230, 230), 1, cv2.LINE_AA)
        col = _COLORS.get(st.outcome, (255, 255, 255))
        if fovea:
            hf = int(round(fovea * scale)) // 2
            cv2.rectangle(canvas, (p[0] - hf, p[1] - hf), (p[0] + hf, p[1] + hf), col, 1)
        cv2.circle(canvas, p, int(5 * s), col, max(1, int(s)), cv2.LINE_AA)
        cv2.putText(canvas, str(i), (p[0] + int(6 * s), p[1] - int(4 * s)), cv2.FONT_HERSHEY_SIMPLEX, 0.4 * s,
                    (255, 255, 255), max(1, int(s)), cv2.LINE_AA)
        prev, prev_attempt = p, st.attempt
    label = f"frame {recognition.frame_id}" if recognition.accepted else "rejected"
    label += f"  a={recognition.evidence:.2f}  resets={recognition.n_resets}"
    _label(canvas, label, s)
    return canvas


def _label(canvas: np.ndarray, text: str, s: float) -> None:
    """White text on a dark box in the top-left corner."""
    fs, th = 0.45 * s, max(1, int(round(s)))
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, th)
    cv2.rectangle(canvas, (0, 0), (w + 8, h + base + 8), (0, 0, 0), -1)
    cv2.putText(canvas, text, (4, h + 4), cv2.FONT_HERSHEY_SIMPLEX, fs, (255, 255, 255), th, cv2.LINE_AA)


def _scaled(canvas: np.ndarray, scale: float) -> np.ndarray:
    if not scale > 0:
        raise InputError(f"drawing scale must be positive, got {scale!r}")
    if scale == 1.0:
        return canvas
    return cv2.resize(canvas, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)


def draw_frame_features(image: Any, memory: VisualMemory, frame_id: int,
                        highlight: Iterable[int] | dict[int, str] = (), scale: float = 1.0) -> np.ndarray:
    """Draw a learned frame's fixation points -> BGR uint8 (the learned image, any size).

    Points are numbered in learning order; ``highlight``: FLC ids drawn filled (e.g. the
    features found in a recognition), or a dict FLC id -> label (e.g. the fixation number
    of the trace): then only the highlighted points are labelled. Others are hollow blue."""
    canvas = _scaled(_to_bgr(image), scale)
    info = memory.frame_features(frame_id)
    W = canvas.shape[1]
    to_px = W / float(info["size"][0])
    s = max(1.0, W / 320.0)
    labels = {int(k): str(v) for k, v in highlight.items()} if isinstance(highlight, dict) else {
        int(k): "" for k in highlight}
    for i, (k, (x, y)) in enumerate(zip(info["features"], info["points"]), 1):
        p = (int(round(x * to_px)), int(round(y * to_px)))
        filled = int(k) in labels
        cv2.circle(canvas, p, int(5 * s), (0, 200, 0) if filled else (255, 160, 0), -1 if filled else max(1, int(s)),
                   cv2.LINE_AA)
        if isinstance(highlight, dict):  # label only the found features, by fixation number
            text = labels.get(int(k), "")
        else:
            text = str(i)
        cv2.putText(canvas, text, (p[0] + int(6 * s), p[1] - int(4 * s)), cv2.FONT_HERSHEY_SIMPLEX, 0.4 * s,
                    (255, 255, 255), max(1, int(s)), cv2.LINE_AA)
    _label(canvas, f"learned frame {frame_id}", s)
    return canvas
