"""What a recognition returns: its saccade trace and outcome, serialisable (paper §2.2; spec §2).

:class:`Recognition` is the outcome of :meth:`~hippomap.visual_memory.VisualMemory.recognise`: the
accepted frame (or none), every fixation as a :class:`SaccadeStep`, and for an accepted frame the
image correspondences (:func:`correspondences`) and their robust shift (:func:`shift_summary`), what the
cognitive map needs to turn a recognition into a relative pose. Both records round-trip through plain dicts
(``to_dict`` / ``from_dict``), which the mapper's events, the service and the viewer carry. A
recognition also keeps the threshold crossings its attempts made (:class:`Crossing`), from which
:func:`place_choice` names a place (docs/MODEL.md items 128 and 129).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputError

__all__ = [
    "PLACE_ACCEPTED",
    "PLACE_LOOKED",
    "Crossing",
    "Recognition",
    "SaccadeStep",
    "correspondences",
    "leading",
    "place_choice",
    "shift_summary",
]


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
    return {"x": float(med[0]), "y": float(med[1]), "mad_x": float(mad[0]), "mad_y": float(mad[1]), "n": int(len(d))}


def correspondences(
    steps: list[SaccadeStep], attempt: int, fid: int, frame_of: np.ndarray, pos: np.ndarray, scale: float
) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """Image correspondences of the accepting ``attempt`` and their robust shift summary (:func:`shift_summary`).

    One per fixation of ``attempt`` whose feature belongs to the accepted frame ``fid`` (``frame_of``: each feature's
    frame): the start fixation with the feature that won it, every confirmed fixation with the predicted feature (the
    microsaccade has snapped the fovea onto it). ``query`` is the fixation, ``memory`` the feature's learned position
    (``pos``, working px of its frame, times the frame's input ``scale``), both in input-image px."""
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
        if k is None or int(frame_of[k]) != fid:
            continue
        mx, my = (float(v) * scale for v in pos[k])
        corr.append(
            {
                "query": [float(st.fixation[0]), float(st.fixation[1])],
                "memory": [mx, my],
                "feature": int(k),
                "outcome": st.outcome,
            }
        )
    return corr, shift_summary(corr)


@dataclass(frozen=True)
class Crossing:
    """A frame whose activity crossed the decision threshold in one attempt of a recognition, which then reset
    before its verification saccades were done: the frame, the attempt, its activity then and the predictions it
    had confirmed."""

    frame: int
    attempt: int
    activity: float
    confirmed: int


def leading(a: np.ndarray, k: int) -> list[tuple[int, float]]:
    """The ``k`` most active frame hypotheses (frame, activity), strongest first."""
    # the same selection as ``nz[np.argsort(-a[nz], kind="stable")[:k]]`` over ``nz = np.flatnonzero(a > 0)``,
    # read through the nonzero values once; ``tolist`` gives the same Python ints and floats as int() and float()
    nz = (a > 0).nonzero()[0]
    if nz.size == 0:
        return []
    v = a[nz]
    top = (-v).argsort(kind="stable")[:k]
    return list(zip(nz[top].tolist(), v[top].tolist()))


#: :attr:`Recognition.reason` of a frame accepted for the crossings of its place (:func:`place_choice`)
PLACE_ACCEPTED = "accepted by its place"
#: :attr:`Recognition.reason` of a frame accepted and verified among its place's frames (docs/MODEL.md item 129)
PLACE_LOOKED = "accepted among its place's frames"


def place_choice(
    crossings: list[Crossing], n: int, span: int, confirmed: int = 0, distinct: int = 1
) -> Crossing | None:
    """The crossing that names a recognition's place (accepted at its end, or looked at): of the crossings with at
    least ``confirmed`` confirmed predictions, the most active (the earliest on ties), once frames learned within
    ``span`` of its frame (that frame included) have crossed in ``n`` of them, ``distinct`` different frames at least;
    else None (docs/MODEL.md items 128 and 129). Key frames learned one after the other are views of one stretch of
    the route: a view between two of them splits its evidence, and each may cross the threshold and miss a far
    prediction, as a view from a step aside does with one frame (item 127). A crossing on the drive of a start
    fixation and one lucky prediction is what chance gives."""
    crossings = [c for c in crossings if c.confirmed >= confirmed]
    if not crossings:
        return None
    best = max(crossings, key=lambda c: c.activity)
    place = [c.frame for c in crossings if abs(c.frame - best.frame) <= span]
    return best if len(place) >= n and len(set(place)) >= distinct else None


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
                    attempt=int(s["attempt"]),
                    fixation=tuple(s["fixation"]),
                    target=None if s.get("target") is None else tuple(s["target"]),
                    predicted_frame=s.get("predicted_frame"),
                    predicted_feature=s.get("predicted_feature"),
                    found_frame=s.get("found_frame"),
                    found_feature=s.get("found_feature"),
                    similarity=float(s.get("similarity", 0.0)),
                    outcome=str(s["outcome"]),
                    evidence=[(int(f), float(a)) for f, a in s.get("evidence", [])],
                    event=s.get("event"),
                )
                for s in d.get("steps", [])
            ]
            return cls(
                frame_id=None if d.get("frame_id") is None else int(d["frame_id"]),
                evidence=float(d.get("evidence") or 0.0),
                steps=steps,
                n_resets=int(d.get("n_resets", 0)),
                confidence=float(d.get("confidence") or 0.0),
                image_size=tuple(d.get("image_size", (0, 0))),
                reason=str(d.get("reason", "")),
                correspondences=[
                    {
                        "query": [float(c["query"][0]), float(c["query"][1])],
                        "memory": [float(c["memory"][0]), float(c["memory"][1])],
                        "feature": int(c.get("feature", -1)),
                        "outcome": str(c.get("outcome", "")),
                    }
                    for c in d.get("correspondences") or []
                ],
                shift=None
                if not d.get("shift")
                else {str(k): (int(v) if k == "n" else float(v)) for k, v in d["shift"].items()},
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
                {
                    "query": [float(c["query"][0]), float(c["query"][1])],
                    "memory": [float(c["memory"][0]), float(c["memory"][1])],
                    "feature": int(c["feature"]),
                    "outcome": str(c["outcome"]),
                }
                for c in self.correspondences
            ],
            "shift": None
            if self.shift is None
            else {k: (int(v) if k == "n" else float(v)) for k, v in self.shift.items()},
        }
