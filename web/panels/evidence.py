"""Panel: the evidence curve of the last recognition (uPlot).

After every fixation the visual memory reports the activity ``a_i`` of the leading frame
hypotheses (``SaccadeStep.evidence``); a frame is accepted when its activity exceeds the
decision threshold θ_dec (paper §3.2, spec §2). The chart plots, against the fixation number,
the three frames that reached the highest activity (the accepted one first) and θ_dec.
Frames absent from a step's leaders are drawn at 0. The series are fixed, so an update sends
only new data and a new title.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

N_CURVES = 3
_COLORS = ("#0a8a3a", "#d9480f", "#5f3dc4")


def evidence_curves(recognition: Mapping[str, Any], n: int = N_CURVES) -> tuple[np.ndarray, list[int], np.ndarray]:
    """(x (K,), frame ids (<= n), curves (n, K)) of a recognition dict; the accepted frame first."""
    steps = recognition.get("steps", [])
    k = len(steps)
    x = np.arange(1, k + 1, dtype=float)
    best: dict[int, float] = {}
    for s in steps:
        for f, a in s.get("evidence", ()):
            best[int(f)] = max(best.get(int(f), 0.0), float(a))
    order = sorted(best, key=lambda f: -best[f])
    acc = recognition.get("frame_id")
    if acc is not None and int(acc) in best:
        order.remove(int(acc))
        order.insert(0, int(acc))
    frames = order[:n]
    curves = np.zeros((n, k))
    col = {f: i for i, f in enumerate(frames)}
    for j, s in enumerate(steps):
        for f, a in s.get("evidence", ()):
            i = col.get(int(f))
            if i is not None:
                curves[i, j] = float(a)
    return x, frames, curves


class EvidencePanel:
    """GUI markdown (which recognition, its verdict) above a uPlot ``evidence`` chart.

    The chart is created once and only its ``data`` is assigned afterwards (the title stays fixed:
    in viser 1.1.1, assigning the title of a mounted chart together with its data left the chart
    blank in the browser of a live session).
    """

    def __init__(self, gui: Any, threshold: float) -> None:
        self.threshold = float(threshold)
        series: list[dict[str, Any]] = [{"label": "fixation"}]
        series += [{"label": f"hypothesis {i + 1}", "stroke": _COLORS[i], "width": 2} for i in range(N_CURVES)]
        series += [{"label": "θ_dec", "stroke": "#868e96", "width": 1, "dash": [4, 4]}]
        self.caption = gui.add_markdown("No recognition yet.")
        self.plot = gui.add_uplot(
            self._data(np.array([1.0, 2.0]), np.zeros((N_CURVES, 2))),
            tuple(series),
            aspect=1.6,
            scales={"x": {"time": False}, "y": {"auto": False, "range": [0.0, 1.05]}},
            axes=({"label": "fixation"}, {"label": "frame activity a"}),
        )
        self._rec_id: Any = None
        self.frames: list[int] = []

    def _data(self, x: np.ndarray, curves: np.ndarray) -> tuple[np.ndarray, ...]:
        return (x, *curves, np.full(len(x), self.threshold))

    def update(self, recognition: Mapping[str, Any] | None) -> bool:
        if recognition is None or recognition.get("id") == self._rec_id:
            return False
        self._rec_id = recognition.get("id")
        x, frames, curves = evidence_curves(recognition)
        if len(x) < 2:  # uPlot needs two points to draw a line
            x = np.array([1.0, 2.0]) if len(x) == 0 else np.r_[x, x[-1] + 1]
            curves = np.zeros((N_CURVES, 2)) if curves.shape[1] == 0 else np.repeat(curves, 2, axis=1)[:, :2]
        self.frames = frames
        names = ", ".join(f"{i + 1} = frame {f}" for i, f in enumerate(frames)) or "no evidence"
        verdict = f"accepted frame {recognition['frame_id']}" if recognition.get("frame_id") is not None else "rejected"
        self.caption.content = f"**Recognition {recognition.get('id')}**: {verdict}. Hypotheses {names}."
        self.plot.data = self._data(x, curves)
        return True
