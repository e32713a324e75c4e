"""Panel: layer toggles — one checkbox per scene layer.

Toggles act on the session's shared scene (every browser viewing the session sees the same
layers; viser has one scene per server). Rejected loop closures start hidden.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable


@dataclass(frozen=True)
class Layer:
    """A toggleable layer: its label, initial visibility, and how to show or hide it."""

    label: str
    visible: bool
    apply: Callable[[bool], None]


class LayersPanel:
    """GUI checkboxes, one per :class:`Layer`."""

    def __init__(self, gui: Any, layers: list[Layer]) -> None:
        self.checkboxes: dict[str, Any] = {}
        for layer in layers:
            box = gui.add_checkbox(layer.label, initial_value=layer.visible)
            layer.apply(layer.visible)

            def on_update(_event: Any, layer: Layer = layer, box: Any = box) -> None:
                layer.apply(bool(box.value))

            box.on_update(on_update)
            self.checkboxes[layer.label] = box
