"""The place-field figure's axes are in metres of the coding area, not matrix cells.

:func:`hippomap.viz.place_field_figure.place_field_figure` draws with matplotlib into a figure it
does not return; the figures it creates are collected (matplotlib's own ``Figure.__init__``,
wrapped, still runs) and their image panels read: each is labelled ``x (m)`` / ``y (m)`` and spans
the requested view in metres (10 cm around the field, or the whole 40 cm area; the close-up of the
field less), inside the area.
"""

from __future__ import annotations

import pytest
from matplotlib.figure import Figure

from hippomap.config import SpatialConfig
from hippomap.spatial_pathway import SpatialPathway
from hippomap.viz.place_field_figure import place_field_figure


@pytest.fixture()
def figures(monkeypatch):
    made: list[Figure] = []
    init = Figure.__init__

    def collect(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(Figure, "__init__", collect)
    return made


@pytest.mark.parametrize("view_m", [0.1, None])
def test_panels_are_in_metres_of_the_coding_area(figures, view_m):
    cfg = SpatialConfig()
    p = SpatialPathway(cfg)
    p.step_increment(0.05, 0.02, 0.3)
    place_field_figure(p.record(), view_m=view_m)
    assert len(figures) == 1
    panels = [ax for ax in figures[0].axes if ax.images]
    assert len(panels) >= 3  # MB and POS per product, and the agreement heatmap
    side = cfg.area_size_m if view_m is None else view_m
    wide = 0
    for ax in panels:
        assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        # in metres (a view in matrix cells would span hundreds), inside the area; the close-up of the
        # field spans a few millimetres, the MB and POS panels the view
        assert 0 < x1 - x0 <= 1.05 * side and 0 < y1 - y0 <= 1.05 * side, (x0, x1, y0, y1)
        assert -0.01 <= x0 and x1 <= cfg.area_size_m + 0.01 and -0.01 <= y0 and y1 <= cfg.area_size_m + 0.01
        wide += min(x1 - x0, y1 - y0) >= 0.5 * side
    assert wide >= 2
