"""The place cells made visible: the iteration of Eq. 9-10 drawn like the paper's Fig. 8.

The paper (§3.1, Fig. 8) shows how a single place field forms: the grid cells' binarised matrices
``MB_n = 1[|G_n - T_n| <= ΔT/2]`` (Eq. 9) and the position matrix ``POS`` shrinking to one field as
they are multiplied in (Eq. 10). :func:`place_field_figure` draws one recorded iteration
(:func:`hippomap.iteration_record.record_iteration`):

* top row: the binarised matrix ``MB_n`` of every cell applied, in order (its module's spacing λ
  and orientation θ in the title);
* bottom row: ``POS`` after each product, with its number of ones and variances against ``T_s``;
  when few ones remain they are ringed, since one grid point (0.05 cm) is far below a pixel;
* right column: the agreement map (fraction of the applied cells whose window a point passes:
  1 exactly on the field) with its colour scale, and a zoom on the field with its centroid.

Axes are in metres of the local coding area (L x L). Rendering uses matplotlib's Agg canvas
directly (no pyplot state), so it is safe from any thread; 1-3 s per figure: draw it on request.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from ..errors import InputError
from ..extras import requires
from ..grid_cells import GridCells
from ..iteration_record import IterationRecord, IterationStep

#: colours of the binarised panels: 0 (dark) and 1 (bright), shown by each row's colour scale
_OFF, _ON = "#141428", "#ffd23c"
_POS_ON = "#3cdcff"


def _pool_any(mask: np.ndarray, step: int) -> np.ndarray:
    """Max-pool a bool (N, N) matrix by ``step`` so thin structures stay visible when shrunk."""
    n = mask.shape[0]
    p = -(-n // step)
    padded = np.zeros((p * step, p * step), bool)
    padded[:n, :n] = mask
    return np.asarray(padded.reshape(p, step, p, step).any(axis=(1, 3)))


def _pool_max(values: np.ndarray, step: int) -> np.ndarray:
    n = values.shape[0]
    p = -(-n // step)
    padded = np.zeros((p * step, p * step), values.dtype)
    padded[:n, :n] = values
    return padded.reshape(p, step, p, step).max(axis=(1, 3))


def _pick_steps(steps: tuple[IterationStep, ...], max_steps: int) -> list[IterationStep]:
    """At most ``max_steps`` applied steps: all of them, or the first ones and the last."""
    if len(steps) <= max_steps:
        return list(steps)
    return list(steps[: max_steps - 1]) + [steps[-1]]


def place_field_figure(
    record: IterationRecord,
    *,
    max_steps: int = 8,
    view_m: float | None = 0.1,
    title: str | None = None,
    dpi: int = 90,
    vertical: bool = False,
) -> np.ndarray:
    """Draw ``record`` as an RGB uint8 image (see module doc).

    ``view_m`` is the side of the square drawn around the field (None: the whole coding area). The
    grid spacing (0.5-2 cm) is tens of matrix cells, so a 10 cm view shows the matrices at their own
    resolution; the whole 40 cm area must be shrunk and its finest lattices alias. ``vertical`` stacks
    the products downwards (MB | POS per row, for a narrow side panel) instead of across."""
    with requires("viz", "the place-field figure"):
        from matplotlib.backends.backend_agg import FigureCanvasAgg

    if max_steps < 2:
        raise InputError(f"max_steps = {max_steps} must be >= 2")
    applied = record.applied
    shown = _pick_steps(applied, max_steps)
    panels = _Panels.layout(record, _view_window(record, view_m), max(len(shown), 1) + 1, dpi, vertical)
    grid = GridCells(record.cfg)
    for j, s in enumerate(shown):
        _draw_product(panels, record, grid, j, s, applied.index(s) + 1)
    ag = _draw_agreement(panels, record, len(applied))
    _draw_field_zoom(panels, record, ag)
    _draw_key(panels)
    panels.fig.suptitle(_heading(record, panels, len(shown), title), fontsize=9)
    panels.fig.canvas.draw()
    rgba = np.asarray(cast(FigureCanvasAgg, panels.fig.canvas).buffer_rgba())  # attached in _Panels.layout
    return np.ascontiguousarray(rgba[:, :, :3])


def _view_window(record: IterationRecord, view_m: float | None) -> tuple[int, int, int, int]:
    """The matrix cells drawn, ``(x0, y0, x1, y1)`` (end exclusive): the whole area, or a ``view_m`` square
    around the field (around the last position set when no field formed), kept inside the area."""
    N, res = record.size, record.resolution
    if view_m is None or view_m >= N * res:
        return 0, 0, N, N
    if view_m <= 4 * res:
        raise InputError(f"view_m = {view_m} must exceed 4 matrix cells ({4 * res} m)")
    w = int(round(view_m / res))
    if record.field is not None:
        c = np.array(record.field.centroid) / res
    else:
        last = record.steps[-1].position if record.steps else np.arange(1)
        iy, ix = np.divmod(last, N)
        c = np.array([ix.mean(), iy.mean()])
    a0, b0 = (np.clip(np.rint(c - w / 2), 0, N - w)).astype(int)
    return int(a0), int(b0), int(a0 + w), int(b0 + w)


@dataclass
class _Panels:
    """The figure and its grid of panels: ``cols`` columns of products plus the right column (agreement map and
    field zoom), and where the drawn window (``window`` = x0, y0, x1, y1 in matrix cells) lies in metres."""

    fig: Any
    gs: Any
    cols: int
    vertical: bool
    window: tuple[int, int, int, int]
    size: int
    resolution: float

    @classmethod
    def layout(
        cls, record: IterationRecord, window: tuple[int, int, int, int], cols: int, dpi: int, vertical: bool
    ) -> "_Panels":
        """The figure with its grid: products across (MB row over POS row), or downwards when ``vertical``."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        if vertical:
            height = 2.05 * cols + 2.2
            fig = Figure(figsize=(5.4, height), dpi=dpi, facecolor="white")
            gs = fig.add_gridspec(
                cols,
                3,
                width_ratios=[1.0, 1.0, 0.07],
                wspace=0.5,
                hspace=0.55,
                left=0.12,
                right=0.86,
                top=1.0 - 1.45 / height,
                bottom=0.85 / height,
            )
        else:
            fig = Figure(figsize=(2.35 * cols + 0.9, 5.6), dpi=dpi, facecolor="white")
            gs = fig.add_gridspec(
                2,
                cols + 1,
                width_ratios=[1.0] * cols + [0.07],
                wspace=0.38,
                hspace=0.42,
                left=0.045,
                right=0.955,
                top=0.84,
                bottom=0.15,
            )
        FigureCanvasAgg(fig)
        return cls(fig, gs, cols, vertical, window, record.size, record.resolution)

    @property
    def whole(self) -> bool:
        """Whether the panels show the whole coding area."""
        return self.window == (0, 0, self.size, self.size)

    @property
    def crop(self) -> tuple[slice, slice]:
        """The drawn window as a slice of an (N, N) matrix (rows = y, columns = x)."""
        a0, b0, a1, b1 = self.window
        return (slice(b0, b1), slice(a0, a1))

    @property
    def pool(self) -> int:
        """Matrix cells pooled into one image pixel, so a panel is at most 256 pixels wide."""
        a0, b0, a1, b1 = self.window
        return max(1, -(-max(a1 - a0, b1 - b0) // 256))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """The drawn window in metres (each matrix cell is a res x res square)."""
        a0, b0, a1, b1 = self.window
        res = self.resolution
        return (a0 * res, a1 * res, b0 * res, b1 * res)

    def add(self, row: int, j: int):
        """A new axes: row 0 = MB panels, row 1 = POS panels, column j; j = cols is the colour bar."""
        if self.vertical:
            spec = self.gs[j, row] if j < self.cols else self.gs[self.cols - 1, 2]
        else:
            spec = self.gs[row, j]
        return self.fig.add_subplot(spec)

    def frame(self, ax, zoom: bool = False) -> None:
        """Ticks and axis labels in metres: five round ticks over the whole area, else about four."""
        ax.tick_params(labelsize=7, length=2)
        if not zoom and self.whole:
            ticks = np.round(np.linspace(0.0, (self.size - 1) * self.resolution, 5), 3)
            ax.set_xticks(ticks)
            ax.set_yticks(ticks)
        else:
            ax.xaxis.set_major_locator(_locator())
            ax.yaxis.set_major_locator(_locator())
        ax.set_xlabel("x (m)", fontsize=7, labelpad=1)
        ax.set_ylabel("y (m)", fontsize=7, labelpad=1)


def _draw_product(panels: _Panels, record: IterationRecord, grid: GridCells, j: int, s: IterationStep, k: int) -> None:
    """Column ``j``: the ``k``-th applied cell's MB_n (top, with its module's spacing and orientation from
    ``grid``) and POS after its product (bottom), the last ones ringed when too few to see."""
    from matplotlib.colors import ListedColormap

    N, res = record.size, record.resolution
    ax = panels.add(0, j)
    ax.imshow(
        _pool_any(record.window_matrix(s)[panels.crop], panels.pool),
        origin="lower",
        extent=panels.extent,
        cmap=ListedColormap([_OFF, _ON]),
        vmin=0,
        vmax=1,
        interpolation="nearest",
    )
    ax.set_title(
        f"MB of cell {s.cell}  (#{k})\nλ={100 * grid.spacing[s.cell]:.2f} cm, "
        f"θ={np.degrees(grid.orientation[s.cell]) % 360:.0f}°",
        fontsize=7.5,
    )
    panels.frame(ax)
    ax = panels.add(1, j)
    pos = record.position_matrix(s)
    ax.imshow(
        _pool_any(pos[panels.crop], panels.pool),
        origin="lower",
        extent=panels.extent,
        cmap=ListedColormap([_OFF, _POS_ON]),
        vmin=0,
        vmax=1,
        interpolation="nearest",
    )
    n_ones = int(s.position.size)
    if n_ones <= 400:  # too few to see at this scale: ring them
        a0, b0, a1, b1 = panels.window
        iy, ix = np.divmod(s.position, N)
        inside = (ix >= a0) & (ix < a1) & (iy >= b0) & (iy < b1)
        iy, ix = iy[inside], ix[inside]
        ax.scatter((ix + 0.5) * res, (iy + 0.5) * res, s=60, facecolors="none", edgecolors="#ff3c78", linewidths=1.0)
    sx, sy = s.variance
    ax.set_title(
        f"POS after {k} product{'s' if k > 1 else ''}\n{n_ones} one{'s' if n_ones != 1 else ''}"
        + (f", S={1e4 * max(sx, sy):.3g} cm²" if n_ones <= 5000 else ""),
        fontsize=7.5,
        color="#b4005a" if s.single else "black",
    )
    panels.frame(ax)


def _draw_agreement(panels: _Panels, record: IterationRecord, n_applied: int) -> np.ndarray:
    """Right column, top: the agreement map with its colour scale. Returns the full (N, N) map."""
    ax = panels.add(0, panels.cols - 1)
    ag = record.agreement()
    im_ag = ax.imshow(
        _pool_max(ag[panels.crop], panels.pool),
        origin="lower",
        extent=panels.extent,
        cmap="inferno",
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
    )
    ax.set_title(f"agreement of the {n_applied} cells\n(1 = every window passes)", fontsize=7.5)
    panels.frame(ax)
    cax = panels.add(0, panels.cols)
    cb = panels.fig.colorbar(im_ag, cax=cax)
    cb.set_label("fraction of cells", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    return ag


def _draw_field_zoom(panels: _Panels, record: IterationRecord, ag: np.ndarray) -> None:
    """Right column, bottom: a zoom on the place field (its points and centroid over the agreement map), or a
    note that none formed."""
    ax = panels.add(1, panels.cols - 1)
    f = record.field
    if f is None:
        ax.text(
            0.5,
            0.5,
            "no single field\n(the cells ran out)",
            ha="center",
            va="center",
            fontsize=9,
            transform=ax.transAxes,
        )
        ax.set_axis_off()
        return
    N, res = record.size, record.resolution
    cx, cy = f.centroid
    half = max(0.004, 12 * res)
    x0 = int(np.clip(np.floor((cx - half) / res), 0, N - 1))
    x1 = int(np.clip(np.ceil((cx + half) / res) + 1, 1, N))
    y0 = int(np.clip(np.floor((cy - half) / res), 0, N - 1))
    y1 = int(np.clip(np.ceil((cy + half) / res) + 1, 1, N))
    ax.imshow(
        ag[y0:y1, x0:x1],
        origin="lower",
        extent=(x0 * res, x1 * res, y0 * res, y1 * res),
        cmap="inferno",
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
    )
    iy, ix = np.divmod(f.indices, N)
    ax.scatter((ix + 0.5) * res, (iy + 0.5) * res, s=14, c=_POS_ON, marker="s", linewidths=0)
    ax.plot([cx + 0.5 * res], [cy + 0.5 * res], "+", color="#ff3c78", ms=12, mew=1.6)
    ax.set_title(
        f"place field: {len(f)} point{'s' if len(f) != 1 else ''}\ncentre ({cx:.4f}, {cy:.4f}) m", fontsize=7.5
    )
    panels.frame(ax, zoom=True)


def _draw_key(panels: _Panels) -> None:
    """The binary rows' colour scale and the markers, as a key under the panels."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    panels.fig.legend(
        handles=[
            Patch(facecolor=_OFF, edgecolor="grey", label="0"),
            Patch(facecolor=_ON, edgecolor="grey", label="MB = 1 (inside the cell's window)"),
            Patch(facecolor=_POS_ON, edgecolor="grey", label="POS = 1 (inside every window so far)"),
            Line2D([], [], marker="o", ls="", mfc="none", mec="#ff3c78", label="last ones (ringed)"),
            Line2D([], [], marker="+", ls="", color="#ff3c78", label="field centroid"),
        ],
        loc="lower center",
        ncol=2 if panels.vertical else 5,
        fontsize=7.5,
        frameon=False,
        bbox_to_anchor=(0.5, 0.0),
    )


def _heading(record: IterationRecord, panels: _Panels, n_shown: int, title: str | None) -> str:
    """The figure's title and its subtitle (the iteration's figures, the window, the steps not shown); wrapped
    at its separators in a vertical figure."""
    n_applied = len(record.applied)
    skipped = sum(1 for s in record.steps if not s.applied)
    res = record.resolution
    L = (record.size - 1) * res
    head = title or "Place cells: grid-cell windows multiplied until one field remains (Eq. 9-10, Fig. 8)"
    sub = (
        f"{n_applied} products, {skipped} skipped · window ΔT = {record.cfg.window:g} g_max · "
        f"T_s = {1e4 * record.cfg.variance_threshold_m2:g} cm² · coding area {L:.2f} m × {L:.2f} m, "
        f"δ = {100 * res:g} cm"
    )
    if not panels.whole:
        a0, b0, a1, b1 = panels.window
        sub += f" · panels show {100 * (a1 - a0) * res:.0f} cm × {100 * (b1 - b0) * res:.0f} cm around the field"
    if n_applied > n_shown:
        sub += f" · products {n_shown}…{n_applied - 1} not shown"
    if panels.vertical:  # a narrow figure: wrap the subtitle at its separators
        lines, cur = [], ""
        for part in sub.split(" · "):
            if cur and len(cur) + len(part) + 3 > 62:
                lines.append(cur)
                cur = part
            else:
                cur = part if not cur else cur + " · " + part
        sub = "\n".join(lines + [cur])
        head = title or "Place cells: windows multiplied to one field\n(Eq. 9-10, the paper's Fig. 8)"
    return head + "\n" + sub


def _locator():
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(4)


def place_field_png(record: IterationRecord, **kwargs) -> bytes:
    """:func:`place_field_figure` encoded as PNG."""
    import cv2

    img = place_field_figure(record, **kwargs)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:  # pragma: no cover - cv2 encodes any uint8 RGB image
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()
