"""Panel: the list of loop closures; choosing one shows its two frames and its saccade trace.

Each entry is one loop decision (:class:`hippomap.cognitive_map.LoopDecision`), newest first:
its id, the two nodes it joins and its time. Its label never changes with its status (a pending
hypothesis may later be accepted or rejected, an accepted one fade), so the choice survives updates;
the status, whether the map uses it (its link's robust weight) and the reason are shown under the
list. Choosing an entry calls back into the viewer, which fetches the query frame and the
recognised key frame from the session, draws the trace on the query (:func:`web.images.pair_panel`)
and marks the loop in the scene.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from hippomap.cognitive_map import LoopDecision
from hippomap.robust_kernel import USED_WEIGHT, is_used

from ..images import placeholder

NONE = "(choose a loop closure)"


def loop_label(d: LoopDecision) -> str:
    return f"#{d.id}  node {d.from_node} → {d.hypothesis.node}  t={d.hypothesis.time:.1f}s"


def loop_details(d: LoopDecision, weight: float = float("nan")) -> str:
    """The details of a loop decision as markdown; ``weight`` is its link's robust weight now (NaN: no
    link): an accepted closure below ``USED_WEIGHT`` has been faded by the kernel and is not used."""
    meta = d.hypothesis.meta
    status = d.status
    if status == "accepted":
        status = "accepted, used" if is_used(d.status, weight) else "accepted, faded"
    rows = [
        f"**loop {d.id}: {status}** — {d.reason or '…'}",
        f"node {d.from_node} (then current) → node {d.hypothesis.node} (recognised)",
        f"evidence {d.hypothesis.evidence:.2f}, source {d.hypothesis.source}",
    ]
    if "frame" in meta:
        rows.append(f"key frame {meta['frame']}, recognition {meta.get('recognition')}")
    if not np.isnan(weight):
        rows.append(f"robust weight {weight:.3f} (used at {USED_WEIGHT:g} or more)")
    if not np.isnan(d.gate_distance):
        rows.append(f"place-code gate {d.gate_distance:.2f} m < {d.gate_limit:.2f} m")
    return "  \n".join(rows)


class LoopsPanel:
    """GUI dropdown ``loop closures``, a details markdown and the pair image."""

    def __init__(self, gui: Any, on_select: Callable[[int | None], None], max_listed: int, width: int) -> None:
        self.max_listed = max_listed
        self.dropdown = gui.add_dropdown("loop closure", (NONE,), initial_value=NONE)
        self.details = gui.add_markdown("No loop closure chosen.")
        self.image = gui.add_image(
            placeholder(2 * width + 4, width * 3 // 4, "choose a loop closure"),
            label="query frame + trace | recognised key frame",
            format="jpeg",
        )
        self._labels: dict[str, int] = {}
        self._options: tuple[str, ...] = (NONE,)
        self._on_select = on_select

        def changed(_event: Any) -> None:
            self._on_select(self.selected_id)

        self.dropdown.on_update(changed)

    @property
    def selected_id(self) -> int | None:
        return self._labels.get(str(self.dropdown.value))

    def update(self, decisions: Sequence[LoopDecision]) -> bool:
        """Offer the newest ``max_listed`` decisions; returns whether the list changed."""
        shown = list(decisions)[::-1][: self.max_listed]
        labels = {loop_label(d): d.id for d in shown}
        options = (NONE, *labels)
        if options == self._options:
            return False
        self._labels = labels
        self._options = options
        self.dropdown.options = options
        return True

    def show(self, decision: LoopDecision | None, image: np.ndarray | None, weight: float = float("nan")) -> None:
        """Show a chosen loop's details (``weight``: its link's robust weight) and frames (or clear)."""
        if decision is None:
            self.details.content = "No loop closure chosen."
            return
        self.details.content = loop_details(decision, weight)
        if image is not None:
            self.image.image = image

    def refresh(self, decision: LoopDecision, weight: float) -> None:
        """Rewrite the chosen loop's details if its status or robust weight has changed since shown
        (the kernel revises the weight whenever the map is solved; the frames stay)."""
        text = loop_details(decision, weight)
        if text != self.details.content:
            self.details.content = text
