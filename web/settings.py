"""Viewer settings: update rates, chunk sizes, idle timeout, colours.

These are presentation settings, not model parameters, so they live here and not in
``hippomap/config.py``. Frozen so one instance can be shared by every session viewer.
"""

from __future__ import annotations

from dataclasses import dataclass

RGB = tuple[int, int, int]


@dataclass(frozen=True)
class ViewerSettings:
    """How often and how much a session viewer sends to the browser."""

    graph_hz: float = 5.0
    """Map graph, trajectories, loops, place field and stats per second (VIEWER.md: ~5 Hz)."""
    camera_hz: float = 10.0
    """Latest camera frame per second (VIEWER.md: ~10 Hz)."""
    idle_timeout_s: float = 60.0
    """A viewer with no browser connected for this long is closed (its viser server stopped)."""
    chunk_size: int = 4096
    """Items (nodes, links, trajectory samples) per sealed scene chunk: sent once, resent only when a
    relaxation moves one of its items (see :mod:`web.scene.chunks`)."""
    tail_size: int = 256
    """Items per tail chunk (the growing end of a layer): an append resends at most this many."""
    move_tolerance_m: float = 0.01
    """A chunk is resent when one of its points moved further than this since it was last sent."""
    trajectory_spacing_m: float = 0.05
    """Trajectories are drawn through one odometry step every so many metres of path..."""
    trajectory_budget: int = 10000
    """...and at most this many steps each: beyond it the spacing doubles (a long run is drawn coarser)."""
    max_loops_listed: int = 200
    """Loop closures offered in the panel's list (the newest ones)."""
    camera_width: int = 320
    """Width (px) the camera image is scaled to before JPEG encoding."""
    thumbnail_width: int = 160
    """Width (px) of the accepted key frame's thumbnail beside the saccade trace."""
    place_field_pixels: int = 161
    """Side (px) of the place-field heatmap drawn over the coding area."""
    place_field_hz: float = 2.0
    """Place-field heatmaps per second at most (each costs ~10-20 ms: Eq. 9 over the full tables)."""
    jpeg_quality: int = 80
    node_size_m: float = 0.06
    link_thickness_m: float = 0.015
    trajectory_thickness_m: float = 0.02
    loop_thickness_m: float = 0.05
    color_node: RGB = (40, 40, 40)
    color_keyframe_node: RGB = (0, 120, 255)
    color_link: RGB = (150, 150, 150)
    color_loop_link: RGB = (0, 190, 60)
    color_odometry: RGB = (248, 200, 150)
    """Raw odometry: a faded orange, so its drift stays readable under the map without dominating it."""
    color_corrected: RGB = (30, 90, 220)
    color_ground_truth: RGB = (0, 165, 165)
    color_loop_accepted: RGB = (0, 200, 70)
    color_loop_rejected: RGB = (220, 40, 40)
    color_loop_faded: RGB = (230, 160, 0)
    """Accepted loop closures the robust kernel has faded (weight below 0.5): amber, between used and rejected."""
    color_robot: RGB = (200, 0, 160)
    show_odometry: bool = True
    """Whether the raw odometry layer starts shown (each viewer can toggle it)."""
    fit_margin: float = 1.15
    """The camera is fitted so that the map's bounding box times this margin fills the view."""
    replay_max_nodes: int = 100000
    """The time slider's replay draws at most this many nodes (every k-th beyond it)."""

    def __post_init__(self) -> None:
        for name in (
            "graph_hz",
            "camera_hz",
            "place_field_hz",
            "idle_timeout_s",
            "move_tolerance_m",
            "trajectory_spacing_m",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"ViewerSettings.{name} = {getattr(self, name)!r} must be > 0")
        for name in (
            "chunk_size",
            "tail_size",
            "trajectory_budget",
            "max_loops_listed",
            "camera_width",
            "thumbnail_width",
            "place_field_pixels",
            "replay_max_nodes",
        ):
            if int(getattr(self, name)) < 2:
                raise ValueError(f"ViewerSettings.{name} = {getattr(self, name)!r} must be >= 2")
        if not self.fit_margin >= 1.0:
            raise ValueError(f"ViewerSettings.fit_margin = {self.fit_margin!r} must be >= 1")
        if self.tail_size > self.chunk_size:
            raise ValueError(
                f"ViewerSettings.tail_size = {self.tail_size} must not exceed chunk_size = {self.chunk_size}"
            )
