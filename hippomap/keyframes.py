"""The mapper's key frames: when a frame becomes one, where each was taken, and which of them a
recognition may name from where the robot stands (paper §2.2 key frames; docs/MODEL.md items 24,
27, 44, 45, 92, 95, 114, 115).

:class:`KeyFrames` is the part of :class:`~hippomap.mapper.Mapper` that holds, per key frame, its
node, its pose in that node's frame (``frame_offset``) and the odometric path length when it was
learned (``frame_path``), and answers five questions: is this frame a key frame (distance or turn,
further apart on a familiar path, and some seconds apart for a fast robot), is this key frame
recognised at all (``recognition_every_s``), was a key frame learned long enough ago to be
recognised as a return, could its view face the robot's way at all, and was it learned near the
key frame the last recognition named (``sequence_window_m``); and it plans a key frame's searches (that
sequence primed, ``sequence_prior``, or searched first; a global search when one is due). It keeps the
clocks these need (:data:`_CLOCKS`).
"""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .geometry import wrap_angle

if TYPE_CHECKING:
    from .config import HippomapConfig
    from .map_reuse import ReuseMap

#: the frame times :class:`KeyFrames` keeps: of the last key frame and of the last recognised key frame
_CLOCKS = ("time_at_keyframe", "time_at_recognition")


class KeyFrames:
    """Key-frame bookkeeping and selection of :class:`~hippomap.mapper.Mapper` (a mixin: the mapper
    owns the clocks, the path and the map it reads)."""

    config: HippomapConfig
    cmap: ReuseMap
    distance: float
    distance_at_keyframe: float
    time_at_keyframe: float  # frame time of the last key frame
    time_at_recognition: float  # frame time of the last key frame that was recognised
    turn: float
    turn_at_keyframe: float
    frames_seen: int
    familiar: bool
    familiar_since: float
    _frame_distance: float
    _frame_turn: float
    frame_offset: dict[int, tuple[float, float, float]]
    frame_node: dict[int, int]
    frame_path: dict[int, float]
    sequence_frame: int | None
    global_search_path: float  # odometric path at the last global search

    def _is_keyframe(self, t: float, previous_t: float | None) -> bool:
        """Whether the frame at time ``t`` (the frame before it at ``previous_t``, None for none) is a key frame: by
        distance or turn since the last key frame, further apart in metres and in seconds on a familiar path
        (``keyframe_familiar_*``); a key frame made by distance also waits ``keyframe_seconds`` (or
        ``keyframe_familiar_seconds``) after the last one."""
        m = self.config.mapper
        if m.keyframe_interval is not None:
            return (self.frames_seen - 1) % m.keyframe_interval == 0
        # the frame nearest to the threshold: it may fall short by half the motion since the
        # previous frame, so that the spacing does not depend on the frame rate
        moved, turned = self.distance - self._frame_distance, self.turn - self._frame_turn
        waited = math.inf if previous_t is None else t - previous_t
        self._frame_distance, self._frame_turn = self.distance, self.turn
        # familiar: the last key frames verified loops over at least keyframe_familiar_after_m of path
        long_familiar = self.familiar and self.distance - self.familiar_since >= m.keyframe_familiar_after_m
        familiar = m.keyframe_familiar_distance_m if long_familiar else None
        dist = m.keyframe_distance_m if familiar is None else familiar
        far = self.distance - self.distance_at_keyframe >= dist - moved / 2
        wait = m.keyframe_seconds if familiar is None else m.keyframe_familiar_seconds
        if far and wait is not None:  # and long enough ago
            far = t - self.time_at_keyframe >= wait - waited / 2
        return far or self.turn - self.turn_at_keyframe >= m.keyframe_turn_rad - turned / 2

    def _recognition_due(self, t: float) -> bool:
        """The key frame at ``t`` is recognised: ``recognition_every_s`` since the last key frame that was, or
        always while lost or without the option."""
        every = self.config.mapper.recognition_every_s
        return every is None or self.cmap.lost or t - self.time_at_recognition >= every

    def _clock_state(self) -> dict[str, float | None]:
        """The key frames' clocks (:data:`_CLOCKS`) for a snapshot; None for none yet."""
        return {k: None if math.isinf(getattr(self, k)) else float(getattr(self, k)) for k in _CLOCKS}

    def _set_clocks(self, meta: dict[str, Any] | None = None) -> None:
        """The key frames' clocks from a snapshot's ``meta`` (one written before they existed has none), or none
        yet (-inf: a new mapper, or a new run on a saved map, whose clock may differ)."""
        for k in _CLOCKS:
            v = (meta or {}).get(k)
            setattr(self, k, -math.inf if v is None else float(v))

    def _recognisable(self, frames: np.ndarray) -> list[int]:
        """The key frames a recognition may name, sorted: those learned at least
        ``recognition_min_path_m`` of path ago. A camera still sees the scene of a key frame it
        took a few metres back, so recognising it is not a return to a place: measured on the
        simulated worlds, such matches named frames 1.5-2.5 m back along the robot's own track
        and pulled the map short when they were verified."""
        f = np.asarray(frames, dtype=np.int64).reshape(-1)
        p = self._lookup(self._frame_array("frame_path", float), f, -math.inf)
        return np.unique(f[self.distance - p >= self.config.mapper.recognition_min_path_m]).tolist()

    def _facing(self, frames: list[int]) -> list[int]:
        """Of ``frames``, those whose view could face the robot's way (``recognition_view_rad``): the
        key frame's heading on the map, within ``recognition_view_rad`` of the robot's (at most
        ``recognition_view_fovs`` fields of view when the camera's is known), plus
        ``recognition_view_rad_per_m`` per metre of drift path (the path since the last verified
        closure, or since the key frame was learned if shorter: the map's headings drift as its
        positions do). A camera turned further than that sees none of what the key frame saw, so
        no saccade is spent on it."""
        m = self.config.mapper
        if m.recognition_view_rad is None or not frames:
            return frames
        bound = m.recognition_view_rad
        if m.recognition_view_fovs is not None and m.camera_hfov_deg is not None:
            bound = min(bound, m.recognition_view_fovs * math.radians(m.camera_hfov_deg))
        cm = self.cmap
        f = np.asarray(frames, dtype=np.int64)
        nodes = self._lookup(self._frame_array("frame_node", int, -1), f, -1).astype(np.int64)
        turn = self._lookup(self._frame_array("frame_offset", lambda v: v[2], 0.0), f, 0.0)
        heading = cm.poses[np.maximum(nodes, 0), 2] + turn
        robot = cm.robot_map_pose()[2]
        drift = np.minimum(
            cm.path_since_verified, self.distance - self._lookup(self._frame_array("frame_path", float), f, 0.0)
        )
        keep = (nodes >= 0) & (np.abs(wrap_angle(heading - robot)) <= bound + m.recognition_view_rad_per_m * drift)
        return f[keep].tolist()

    @staticmethod
    def _lookup(arr: np.ndarray, f: np.ndarray, missing: float) -> np.ndarray:
        """``arr[f]``, with ``missing`` for ids outside it."""
        out = np.full(f.shape, missing, dtype=float)
        known = (f >= 0) & (f < len(arr))
        out[known] = arr[f[known]]
        return out

    def _frame_array(self, name: str, pick: Callable[[Any], float], missing: float = -math.inf) -> np.ndarray:
        """The dict attribute ``name`` (key frame -> value) as an array indexed by frame id
        (``missing`` where unknown; ``pick`` turns a value into a number), so that the key frames
        are read without a Python loop over them (the global search passes all of them). Kept in
        step with the dict: its newest entries (insertion order) are added when it has grown, and
        it is rebuilt when the dict was replaced (a restored snapshot)."""
        d = getattr(self, name)
        key = "_arr_" + name
        cache = self.__dict__.get(key)
        if cache is None or cache[0] is not d or cache[2] > len(d):
            cache = (d, np.zeros(0), 0)
        _, arr, n = cache
        if len(d) > n:
            new = list(itertools.islice(reversed(d.items()), len(d) - n))
            keys = np.array([k for k, _ in new], dtype=np.int64)
            if int(keys.max()) >= len(arr):
                arr = np.concatenate([arr, np.full(max(int(keys.max()) + 1 - len(arr), len(arr)), missing)])
            arr[keys] = [pick(v) for _, v in new]
        self.__dict__[key] = (d, arr, len(d))
        return arr

    def _sequence(self, frames: list[int]) -> list[int]:
        """Of ``frames``, those learned within ``sequence_window_m`` of path of the key frame the last
        recognition named (:attr:`sequence_frame`): a robot retracing its path meets the old path's key
        frames in their order, so the next match is most likely among them; [] without one."""
        w = self.config.mapper.sequence_window_m
        if w is None or self.sequence_frame is None or not frames:
            return []
        at = self.frame_path.get(self.sequence_frame)
        if at is None:
            return []
        f = np.asarray(frames, dtype=np.int64)
        p = self._lookup(self._frame_array("frame_path", float), f, -math.inf)
        return f[np.abs(p - at) <= w].tolist()

    def _searches(self, candidates: list[int]) -> list[tuple[list[int], str, list[int] | None]]:
        """The gated searches of a key frame among ``candidates``, in order, as (key frames, search, primed key
        frames): all at once with the old path's sequence (:meth:`_sequence`) primed when ``sequence_prior`` is
        set (docs/MODEL.md item 115); else the sequence first, then the rest (item 114); without one, all at once."""
        seq = self._sequence(candidates)
        if not seq:
            return [(candidates, "gated", None)]
        if self.config.mapper.sequence_prior is not None:
            return [(candidates, "gated", seq)]
        return [(seq, "sequence", None), (np.setdiff1d(candidates, seq).tolist(), "gated", None)]

    def _global_search_due(self) -> bool:
        """A global search (every recognisable key frame, gate or not) is due: the map has gone
        ``global_search_after_m`` of path without a verified closure, and the last global search
        is ``global_search_every_m`` behind. Not while localising in a saved map (it already
        searches the whole saved map while lost)."""
        m = self.config.mapper
        return (
            m.global_search_after_m is not None
            and not self.cmap.localise_only
            and not self.cmap.lost
            and self.cmap.path_since_verified >= m.global_search_after_m
            and self.distance - self.global_search_path >= m.global_search_every_m
        )
