"""Panel: layer toggles and the legend that names every layer.

Each browser gets its own toggles (viser's client-scoped GUI): hiding a layer in one browser does
not hide it in another. The shared scene keeps every layer shown; a browser that hides a layer adds
a client-scoped, invisible frame with the layer group's name, which shadows the shared group for
that browser only (viser 1.1 renders a client's own variant of a node name in place of the shared
one, and the shared group's chunks hang below it, including chunks added later), and removes it to
show the layer again. Layers hidden by default (faded and rejected loop closures) are shadowed on connect.

The legend (:func:`legend_html`) is drawn on the canvas in a floating panel, always visible: one
swatch per layer in the layer's own colour and shape, and the place field's colour scale.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from ..settings import RGB, ViewerSettings


@dataclass(frozen=True)
class LayerSpec:
    """A toggleable layer: label, default visibility, the scene groups it covers, legend swatch."""

    key: str
    label: str
    visible: bool
    groups: tuple[str, ...]
    color: RGB | None = None
    shape: str = "line"  # legend swatch: "line", "dot", "bar" (thicker line) or "none"


def layer_specs(s: ViewerSettings) -> list[LayerSpec]:
    """The viewer's layers, in legend order."""
    return [
        LayerSpec("nodes", "map nodes", True, ("/map/nodes",), s.color_node, "dot"),
        LayerSpec("keyframes", "nodes with a key frame", True, (), s.color_keyframe_node, "dot"),
        LayerSpec("links", "map links", True, ("/map/links", "/map/loop_links"), s.color_link),
        LayerSpec("corrected", "map trajectory", True, ("/trajectories/map",), s.color_corrected, "bar"),
        LayerSpec("ground_truth", "ground truth", True, ("/ground_truth",), s.color_ground_truth, "bar"),
        LayerSpec("odometry", "raw odometry", s.show_odometry, ("/trajectories/odometry",), s.color_odometry),
        LayerSpec("accepted", "loop closures (used)", True, ("/loops/accepted",), s.color_loop_accepted),
        LayerSpec("faded", "loop closures (faded by the robust kernel)", False, ("/loops/faded",), s.color_loop_faded),
        LayerSpec("rejected", "loop closures (rejected)", False, ("/loops/rejected",), s.color_loop_rejected),
        LayerSpec("place_field", "place field", True, ("/place_field",), None, "none"),
        LayerSpec("robot", "robot", True, ("/robot",), s.color_robot, "dot"),
    ]


#: inferno at 0, 0.25, 0.5, 0.75, 1 (matplotlib's colour map, as the heatmap uses)
_INFERNO = ("#000004", "#57106e", "#bc3754", "#f98e09", "#fcffa4")


def _swatch(color: RGB | None, shape: str) -> str:
    if color is None or shape == "none":
        return '<span style="display:inline-block;width:22px"></span>'
    c = f"rgb({color[0]},{color[1]},{color[2]})"
    if shape == "dot":
        return (
            f'<span style="display:inline-block;width:22px;text-align:center"><span style="display:inline-block;'
            f'width:9px;height:9px;border-radius:50%;background:{c};vertical-align:middle"></span></span>'
        )
    width = 3 if shape == "bar" else 2
    return (
        f'<span style="display:inline-block;width:22px;height:0;border-top:{width}px solid {c};'
        f'vertical-align:middle"></span>'
    )


def legend_html(specs: list[LayerSpec], ground_truth: bool, visible: dict[str, bool] | None = None) -> str:
    """The legend as HTML: a swatch and label per layer (ground truth only when the session has it;
    layers hidden in this browser greyed), then the place field's colour scale."""
    rows = []
    for sp in specs:
        if sp.key == "place_field":
            continue
        if sp.key == "ground_truth" and not ground_truth:
            continue
        hidden = visible is not None and not visible.get(sp.key, sp.visible)
        style = "opacity:0.4;text-decoration:line-through" if hidden else ""
        rows.append(
            f'<div style="white-space:nowrap;{style}" data-layer="{sp.key}">{_swatch(sp.color, sp.shape)}'
            f" {sp.label}</div>"
        )
    grad = ", ".join(_INFERNO)
    scale = (
        '<div style="margin-top:4px">place field: share of grid cells whose window the place passes'
        f'<div style="height:8px;margin:2px 0 0 0;background:linear-gradient(to right, {grad})"></div>'
        '<div style="display:flex;justify-content:space-between;font-size:10px"><span>0</span>'
        "<span>0.5</span><span>1 (the field, white)</span></div></div>"
    )
    return (
        '<div style="font:12px/1.45 sans-serif;padding:2px 4px" class="hippomap-legend">'
        + "".join(rows)
        + scale
        + "</div>"
    )


class ClientLayers:
    """One browser's layer checkboxes; toggling shadows the layer's groups for that browser only."""

    def __init__(self, client: Any, specs: list[LayerSpec], on_change: Callable[[], None] | None = None) -> None:
        self.client = client
        self.specs = [sp for sp in specs if sp.groups]
        self._shadows: dict[str, Any] = {}
        self._on_change = on_change
        self._replaying = False
        self.visible: dict[str, bool] = {sp.key: sp.visible for sp in specs}
        self.checkboxes: dict[str, Any] = {}
        for sp in self.specs:
            box = client.gui.add_checkbox(sp.label, initial_value=sp.visible)

            def on_update(_event: Any, sp: LayerSpec = sp, box: Any = box) -> None:
                self.set(sp.key, bool(box.value))

            box.on_update(on_update)
            self.checkboxes[sp.key] = box
        for sp in self.specs:
            if not sp.visible:
                self.set(sp.key, False)

    def set(self, key: str, value: bool) -> None:
        """Show or hide layer ``key`` in this browser."""
        sp = next(s for s in self.specs if s.key == key)
        self.visible[key] = value
        self._apply(sp)
        if key in self.checkboxes and bool(self.checkboxes[key].value) != value:
            self.checkboxes[key].value = value
        if self._on_change is not None:
            self._on_change()

    def set_replaying(self, replaying: bool) -> None:
        """While the time slider replays, every live layer is shadowed in this browser (the replay is
        drawn elsewhere); afterwards each layer is back as toggled."""
        if replaying == self._replaying:
            return
        self._replaying = replaying
        for sp in self.specs:
            self._apply(sp)

    def _apply(self, sp: LayerSpec) -> None:
        """Shadow ``sp``'s groups iff the layer is hidden or a replay is shown (one leaf frame per group,
        never a parent of another shadow, so removing one never cascades onto another)."""
        hide = self._replaying or not self.visible.get(sp.key, sp.visible)
        for group in sp.groups:
            have = group in self._shadows
            if hide and not have:
                self._shadows[group] = self.client.scene.add_frame(group, show_axes=False, visible=False)
            elif not hide and have:
                self._shadows.pop(group).remove()

    def shown(self, key: str) -> bool:
        return bool(self.visible.get(key, True))
