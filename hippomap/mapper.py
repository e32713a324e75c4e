"""The whole mapper of the paper's Fig. 1: one object per mapping session.

Odometry drives the place code (grid cells -> place cells). A frame becomes a key frame after
``keyframe_distance_m`` metres of path or ``keyframe_turn_rad`` of turn (or every
``keyframe_interval`` frames, [S]'s rule, when that is set): it is first recognised against the
key frames of the nodes the map's loop gate admits (:meth:`CognitiveMap.loop_candidates`) and
then learned into the visual memory, together with where it was taken relative to its node.
An accepted recognition becomes a :class:`~hippomap.loop_closure.LoopHypothesis` whose offset
is that pose, moved along the key frame's view by the image's scale change (looming, held as
uncertain as it is long) and turned by the image shift of the saccade correspondences when the
camera's field of view is known, and named on the node of the old path nearest the place it
claims (:func:`~hippomap.loop_pose.reanchor`), which the loop closing (:mod:`hippomap.loop_closure`)
verifies and fits before the map closes the loop and relaxes.

Inputs must come in time order; every call returns the events it caused, typed
(:mod:`hippomap.map_events`: the map's, raised while the call ran, and the mapper's own;
``MapEvent.to_dict`` makes them JSON) and never mutates state when it raises ``InputError``.
The reads a service needs are typed query values (:mod:`hippomap.mapper_queries`,
:meth:`Mapper.answer`).
The whole state serialises to bytes (:meth:`Mapper.to_bytes`) and restores to a mapper
whose future outputs are identical.

**Map reuse.** :meth:`Mapper.from_base` starts a new run in a saved map (a snapshot of another
mapper): the map, its key frames and their poses are kept, the run's own odometry starts from
an unknown pose. Until the robot is placed (``lost``), every key frame of the saved map is a
recognition candidate and the loop gate, which needs a pose on the map, is waived: the run's
recognitions of saved key frames are ordinary loop hypotheses, accepted only when
``loop_min_support`` of them agree (cycle consistency) and fitted together; the accepted group
places the run on the map. With ``mapper.mode = 'localise'`` the map adds no node, link or
key frame and never moves: accepted groups only relocalise the robot (:class:`ReuseMap`).
Merging one session into another is a new run from the first session's map fed with the
second session's inputs (docs/MODEL.md).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np

from .config import HippomapConfig
from .errors import InputError
from .geometry import compose, se2_compose
from .inputs import Frame, Odometry, follows
from .keyframes import KeyFrames
from .loop_closure import LoopHypothesis
from .loop_pose import focal_px, looming_offset, reanchor
from .map_events import KeyframeLearned, LoopDecided, MapEvent, RecognitionMade
from .map_reuse import ReuseMap
from .mapper_state import Grow, config_over, join_arrays, pack, split_arrays, unpack
from .robust_kernel import used_flags
from .spatial_pathway import PlaceCode, SpatialPathway
from .visual_memory import VisualMemory

if TYPE_CHECKING:
    from .mapper_queries import Query

T = TypeVar("T")


#: columns of the per-step trajectory store: t, raw odometric pose (x, y, theta), current node, the robot's
#: offset from it as the odometry measured it (dx, dy, dtheta), and the seconds since it arrived at the node
_TRAJ_COLUMNS = 9


class Mapper(KeyFrames):
    """One mapping session: ``step(odometry)`` and ``observe(frame)`` in time order."""

    def __init__(self, config: HippomapConfig | None = None) -> None:
        self.config = config or HippomapConfig()
        self.pathway = SpatialPathway(self.config.spatial, self.config.map.initial_pose)
        self.cmap = ReuseMap(self.config.map)
        self.cmap.configure(self.localise_only, False)
        self.memory = VisualMemory(self.config.visual)
        self.base_nodes = 0  # nodes that came from a saved map (Mapper.from_base)
        self.last_t: float | None = None  # time of the last input of either kind
        self.last_odometry_t: float | None = None
        self.last_frame_t: float | None = None
        self.frames_seen = 0
        self.distance = 0.0  # odometric path length, metres
        self.distance_at_keyframe = -math.inf
        self.global_search_path = -math.inf  # odometric path at the last global search
        self.turn = 0.0  # odometric turn, |radians| summed
        self.turn_at_keyframe = 0.0
        self.familiar = False  # the last key frame's recognition verified a loop (keyframe_familiar_distance_m)
        self.familiar_since = 0.0  # odometric path at the first of the current run of verified key frames
        self.sequence_frame: int | None = None  # the key frame the last recognition named, if the map took it
        self._frame_distance = self._frame_turn = 0.0  # distance and turn at the previous frame
        self._set_clocks()
        self.frame_offset: dict[int, tuple[float, float, float]] = {}  # key frame -> its pose in its node's frame
        self.frame_node: dict[int, int] = {}  # key-frame id -> node id
        self.frame_path: dict[int, float] = {}  # key-frame id -> odometric path length when it was learned
        self.recognitions: list[dict[str, Any]] = []
        self.place: tuple[float, float, float] | None = None  # latest place code p
        self.place_field: PlaceCode | None = None  # latest PlaceCode with its field (not persisted)
        # per odometry step: t, raw odometric pose, current node, robot offset from it, seconds at the node
        self._traj = Grow(_TRAJ_COLUMNS)

    @property
    def localise_only(self) -> bool:
        """``mapper.mode == 'localise'``: recognise and relocalise, never change the map."""
        return self.config.mapper.mode == "localise"

    @property
    def lost(self) -> bool:
        """The robot has no pose on the map yet (a new run in a saved map, not yet recognised)."""
        return self.cmap.lost

    @classmethod
    def from_base(cls, base: "bytes | Mapper", overrides: dict[str, Any] | None = None) -> "Mapper":
        """A new run in a saved map: ``base`` is a snapshot (:meth:`to_bytes`) or a mapper (copied,
        never changed). ``overrides`` (nested, as :meth:`HippomapConfig.with_overrides`) change the
        base's config, e.g. ``{"mapper": {"mode": "localise"}}``; they must keep its visual config,
        which the key frames were learned with.

        Kept: the cognitive map, the visual memory and each key frame's node and pose. New: the
        run's odometry (it starts at ``map.initial_pose`` of its own frame, an unknown pose on the
        map), the spatial pathway, the clocks (the run may start at t = 0 again), the trajectory,
        the recognitions and loop decisions. The path length goes on, plus
        ``recognition_min_path_m``, so that every saved key frame can be recognised at once."""
        data = base.to_bytes() if isinstance(base, Mapper) else base
        if not isinstance(data, (bytes, bytearray)):
            raise InputError(f"from_base needs a mapper snapshot (bytes) or a Mapper, got {type(base).__name__}")
        m = cls.from_bytes(bytes(data))
        if m.cmap.lost and m.cmap.component_from >= 0:
            raise InputError(
                "the saved map holds a run that was never placed on it: its nodes float apart from "
                "the map, so it cannot be a base map"
            )
        if overrides:
            config = config_over(m.config, overrides)
            if config.visual != m.config.visual:
                raise InputError(
                    "a run in a saved map must keep the saved map's visual config (its key frames were learned with it)"
                )
            m.config = config
            m.cmap.own_cfg = config.map
        cfg = m.config
        m.pathway = SpatialPathway(cfg.spatial, cfg.map.initial_pose)
        m.last_t = m.last_odometry_t = m.last_frame_t = None
        m.frames_seen = 0
        m.distance += cfg.mapper.recognition_min_path_m
        m.distance_at_keyframe = m.global_search_path = -math.inf
        m._set_clocks()  # the new run's clock may differ
        m.turn_at_keyframe = m.turn
        m.familiar = False
        m.sequence_frame = None  # the new run has recognised nothing yet
        m._frame_distance, m._frame_turn = m.distance, m.turn
        m.recognitions = []
        m.place = None
        m.place_field = None
        m._traj = Grow(_TRAJ_COLUMNS)
        m.base_nodes = int(m.cmap.node_count)
        m.cmap.configure(m.localise_only, False)
        m.cmap.start_run(cfg.map.initial_pose)
        return m

    # ------------------------------------------------------------------ inputs
    def _check_time(self, t: float, last: float | None, what: str) -> None:
        """Each stream's timestamps strictly increase; the two streams may interleave
        freely (a frame may carry the time of an odometry reading)."""
        if not follows(last, t):
            raise InputError(f"{what} timestamp {t!r} does not follow the previous {what} at {last!r}")

    def step(self, odometry: Odometry) -> list[MapEvent]:
        """Feed one odometry reading; returns the events it caused."""
        if not isinstance(odometry, Odometry):
            raise InputError(f"step() takes an Odometry, got {type(odometry).__name__}")
        t = odometry.t
        self._check_time(t, self.last_odometry_t, "odometry")
        if odometry.increment is None and self.last_odometry_t is None:
            inc = (0.0, 0.0, 0.0)  # velocities need a previous time to integrate over
        else:
            dt = t - (self.last_odometry_t if self.last_odometry_t is not None else t)
            inc = odometry.as_increment(dt)
        self.last_t = self.last_odometry_t = t
        code = self.pathway.step_increment(*inc)
        self.distance += math.hypot(inc[0], inc[1])
        self.turn += abs(inc[2])
        events = self.cmap.update(  # localising: no place code, so no new node
            None if code is None or self.localise_only else (code.x, code.y, code.theta), inc, t
        )
        if code is not None:
            self.place = (code.x, code.y, code.theta)
            self.place_field = code
        pose = self.pathway.pose
        cm = self.cmap
        self._traj.append([t, pose[0], pose[1], pose[2], cm.current, *cm.robot_offset, cm.time_at_node])
        return events

    def observe(self, frame: Frame) -> list[MapEvent]:
        """Feed one camera frame; on a key frame: recognise near the place code, then learn.
        Returns the events of this frame: the recognition, the loop decision with the map's
        events it raised (loop pending/accepted/rejected, relaxation), the learned key frame."""
        if not isinstance(frame, Frame):
            raise InputError(f"observe() takes a Frame, got {type(frame).__name__}")
        self._check_time(frame.t, self.last_frame_t, "frame")
        gray = frame.gray()
        self.memory.check_image(gray)  # raises InputError before any state changes
        previous_t, self.last_t, self.last_frame_t = self.last_frame_t, frame.t, frame.t
        self.frames_seen += 1
        if not self._is_keyframe(frame.t, previous_t):
            return []
        events: list[MapEvent] = []
        recognised = False
        if self.place is not None and self.memory.frame_count and self._recognition_due(frame.t):
            self.time_at_recognition = frame.t
            recognised = self._recognise_key_frame(gray, frame.t, events)
        self.distance_at_keyframe = self.distance
        self.time_at_keyframe = frame.t
        self.turn_at_keyframe = self.turn
        # a place is familiar when this key frame's recognition verified a loop (keyframe_familiar_distance_m);
        # familiar_since: where the current run of such key frames began (keyframe_familiar_after_m)
        verified = recognised and self.cmap.path_since_verified <= 0.0
        if verified and not self.familiar:
            self.familiar_since = self.distance
        self.familiar = verified
        if self.localise_only or (recognised and not self.config.mapper.learn_recognised):
            return events
        fid = self.memory.learn(gray)
        if fid is not None:
            node = int(self.cmap.current)
            self.cmap.set_frame(node, fid)
            self.frame_node[int(fid)] = node
            self.frame_offset[int(fid)] = cast(
                "tuple[float, float, float]", tuple(float(v) for v in self.cmap.robot_offset)
            )
            self.frame_path[int(fid)] = float(self.distance)
            events.append(KeyframeLearned(frame.t, int(fid), node))
            events.extend(self.cmap.take_events())
        return events

    def _recognise_key_frame(self, gray: np.ndarray, t: float, events: list[MapEvent]) -> bool:
        """The recognitions of a key frame: among the key frames the loop gate admits that could face the robot's
        way (while lost, every key frame of the saved map), in the searches :meth:`_searches` plans (the old path's
        sequence primed or first); then, when one is due, a global search among all the others. True when the map
        did not reject the hypothesis; the frame it named is where the next key frame's sequence is sought."""
        cm = self.cmap
        frames = cm.frames[: self.base_nodes] if cm.lost else cm.frames[cm.loop_candidates()]
        candidates = self._recognisable(frames[frames >= 0])
        if not cm.lost:  # while lost the robot's heading on the map is unknown
            candidates = self._facing(candidates)
        recognised = False
        for keys, search, primed in self._searches(candidates):
            if keys and not recognised:
                recognised = self._recognise(gray, t, keys, events, search=search, prior=primed)
        if not recognised and self._global_search_due():
            self.global_search_path = self.distance
            every = self._recognisable(cm.frames[cm.frames >= 0])
            others = np.setdiff1d(np.asarray(every, np.int64), np.asarray(candidates, np.int64)).tolist()
            if others:
                recognised = self._recognise(gray, t, others, events, search="global")
        self.sequence_frame = self.recognitions[-1]["frame_id"] if recognised else None
        return recognised

    def _recognise(
        self,
        gray: np.ndarray,
        t: float,
        candidates: list[int],
        events: list[MapEvent],
        search: str = "gated",
        prior: list[int] | None = None,
    ) -> bool:
        """Recognise ``gray`` among ``candidates`` (``prior``: those starting with ``sequence_prior``'s head
        start); a match is offered to the map as a loop hypothesis. Appends the events; True when the map did
        not reject the hypothesis nor leave it waiting for a long group (docs/MODEL.md item 130)."""
        m = self.config.mapper
        bar = m.global_search_give_up_evidence if search == "global" else None
        p = m.sequence_prior or 0.0
        rec = self.memory.recognise(gray, candidates=candidates, give_up_evidence=bar, prior=prior, prior_activity=p)
        rec_id = len(self.recognitions)
        result = {**rec.to_dict(), "search": search, "candidates": len(candidates)}
        if prior:
            result["primed"] = len(prior)
        made = RecognitionMade(rec_id, t, int(self.cmap.current), result)
        self.recognitions.append(made.record())
        events.append(made)
        if rec.frame is None:
            return False
        meta: dict[str, Any] = {"recognition": rec_id, "frame": int(rec.frame)}
        turn = self._view_turn(rec, gray.shape)
        if turn is not None:  # across a wide turn the gate asks for a group (map.loop_oblique_turn_rad)
            meta["view_turn"] = turn
        ahead = self._looming(rec, gray.shape)
        if search != "gated":
            meta["search"] = search
        key_node = node = self.frame_node[int(rec.frame)]
        offset = self._visual_offset(rec, gray.shape, ahead, turn or 0.0)  # None: no shift, no turn
        span = self.config.mapper.reanchor_span
        if span is not None:  # the link names the node nearest the place claimed (MODEL item 103)
            end = self.cmap.node_count - self.config.map.exclude_recent
            node, offset = reanchor(self.cmap.poses, key_node, offset, span, end)
            if node != key_node:
                meta["key_frame_node"] = key_node
        hyp = LoopHypothesis(
            node=node,
            transform=None,
            evidence=float(rec.evidence),
            source="visual",
            time=t,
            meta=meta,
            offset=offset,
            coupling=self._shift_coupling(rec),
            along_sigma=(self.config.mapper.looming_spread or 0.0) * abs(ahead),
        )
        decision = self.cmap.propose_loop(hyp)
        events.append(LoopDecided(t, decision))
        events.extend(self.cmap.take_events())
        return decision.status != "rejected" and not self.cmap.awaits_long_group(decision.id)

    def _shift_coupling(self, rec: Any) -> float:
        """The coupling of a recognition's heading with the robot's offset beside the key frame
        (:attr:`~hippomap.loop_closure.LoopHypothesis.coupling`): ``1 / mapper.view_distance_m`` when the heading
        comes from the image shift (:meth:`_view_turn`) and ``mapper.shift_coupling`` is on; else 0. A scene ``D``
        away shifts by the turn plus the sideways step over ``D``: the shift fixes ``heading + lateral / D``."""
        m = self.config.mapper
        if not m.shift_coupling or m.view_distance_m is None or self._shift_of(rec) is None:
            return 0.0
        return 1.0 / m.view_distance_m

    def _shift_of(self, rec: Any) -> dict[str, Any] | None:
        """The recognition's image shift when it gives a heading (the camera's field of view is known
        and the shift rests on at least two correspondences), else None."""
        shift = getattr(rec, "shift", None)
        if self.config.mapper.camera_hfov_deg is None or not shift or shift.get("n", 0) < 2:
            return None
        return cast("dict[str, Any]", shift)

    def _looming(self, rec: Any, shape: tuple[int, ...]) -> float:
        """How far the robot stands ahead of the matched key frame along its view (m; negative: behind),
        from the looming of the recognition's saccade correspondences
        (:func:`~hippomap.loop_pose.looming_offset`: the scene appears larger when the robot stands ahead of
        the key frame), on the viewing sphere of an image of ``shape`` when ``mapper.looming_on_sphere`` and
        the camera's field of view is known; 0 without ``mapper.view_distance_m`` or a usable pair."""
        m = self.config.mapper
        pairs = getattr(rec, "correspondences", None) or []
        if m.view_distance_m is None or not pairs:
            return 0.0
        hfov = m.looming_hfov_deg
        camera = None if hfov is None else (float(shape[1]), float(shape[0]), hfov)
        d = looming_offset([c["query"] for c in pairs], [c["memory"] for c in pairs], m.view_distance_m, camera=camera)
        return 0.0 if d is None else d

    def _visual_offset(
        self, rec: Any, shape: tuple[int, ...], ahead: float | None = None, turn: float | None = None
    ) -> tuple[float, float, float]:
        """The robot's pose in the matched node's frame as recognition tells it: where the matched key frame was taken,
        moved ``ahead`` along its view (:meth:`_looming` if None), turned by ``turn`` (:meth:`_view_turn` if None)."""
        off = self.frame_offset.get(int(rec.frame), (0.0, 0.0, 0.0))
        ahead = self._looming(rec, shape) if ahead is None else ahead
        turn = (self._view_turn(rec, shape) if turn is None else turn) or 0.0
        if ahead == 0.0 and turn == 0.0:
            return off
        return se2_compose(off, (ahead, 0.0, turn))

    def _view_turn(self, rec: Any, shape: tuple[int, ...]) -> float | None:
        """How far the robot has turned from the matched key frame's view (rad, left positive: a feature further right
        in the query than in memory) by the recognition's image shift; None without the field of view or a shift."""
        shift = self._shift_of(rec)
        hfov = self.config.mapper.camera_hfov_deg
        return None if shift is None or hfov is None else math.atan2(float(shift["x"]), focal_px(shape[1], hfov))

    # ----------------------------------------------------------------- queries
    @property
    def trajectory_times(self) -> np.ndarray:
        return self._traj.view[:, 0].copy()

    def odometry_trajectory(self) -> np.ndarray:
        """(N, 3) raw path-integrated poses, one per odometry step."""
        return self._traj.view[:, 1:4].copy()

    def corrected_trajectory(self) -> np.ndarray:
        """(N, 3) the same steps placed on the current (relaxed) map, each offset from its node
        with the odometry's estimated heading bias taken off (:meth:`CognitiveMap.debiased`)."""
        rows = self.trajectory_rows()
        if not len(rows):
            return np.empty((0, 3))
        return compose(self.cmap.poses[rows[:, 4].astype(np.int64)], rows[:, 5:8])

    def trajectory_rows(self, start: int = 0) -> np.ndarray:
        """Per-step rows from ``start`` on: ``t, x, y, theta`` (raw odometric pose), current
        node, and the robot's offset from it (``dx, dy, dtheta``; its heading with the bias the map
        estimates now taken off over the time the robot had been at the node). Append-only, so a
        viewer copies only what is new."""
        v = self._traj.view[start:]
        rows = v[:, :8].copy()
        rows[:, 5:8] = self.cmap.debiased(v[:, 5:8], v[:, 8])
        return rows

    def stats(self) -> dict[str, Any]:
        decisions = [d.status for d in self.cmap.loop_decisions]
        used = sum(used_flags(self.cmap.loop_decisions, self.cmap.loop_weights()))
        return {
            "odometry_steps": int(self._traj.n),
            "frames": int(self.frames_seen),
            "keyframes": int(self.memory.frame_count),
            "nodes": int(self.cmap.node_count),
            "links": int(self.cmap.link_count),
            "recognitions": len(self.recognitions),
            "mode": self.config.mapper.mode,
            "lost": bool(self.cmap.lost),
            "base_nodes": int(self.base_nodes),
            "loop_closures_accepted": decisions.count("accepted"),
            "loop_closures_rejected": decisions.count("rejected"),
            "loop_closures_used": int(used),
            "distance_m": float(self.distance),
            "last_t": self.last_t,
        }

    def answer(self, query: "Query[T]") -> T:
        """The answer to a typed read (:mod:`hippomap.mapper_queries`); InputError for anything else."""
        from .mapper_queries import run_query

        return run_query(self, query)

    # ------------------------------------------------------------- persistence
    def to_bytes(self) -> bytes:
        """The whole state as bytes (npz of arrays + a JSON header; no pickle:
        :func:`hippomap.mapper_state.pack`)."""
        arrays: dict[str, Any] = {}  # (np.ndarray values: Any for numpy's savez_compressed(**kwds) stub)
        meta = {
            "config": self.config.model_dump(mode="json"),
            "pathway": split_arrays(self.pathway.state_dict(), "pathway", arrays),
            "cmap": split_arrays(self.cmap.state_dict(), "cmap", arrays),
            "memory": split_arrays(self.memory.state_dict(), "memory", arrays),
            "last_t": self.last_t,
            "last_odometry_t": self.last_odometry_t,
            "last_frame_t": self.last_frame_t,
            "frames_seen": self.frames_seen,
            "distance": self.distance,
            "distance_at_keyframe": None if math.isinf(self.distance_at_keyframe) else self.distance_at_keyframe,
            "global_search_path": None if math.isinf(self.global_search_path) else self.global_search_path,
            "frame_node": [[k, v] for k, v in self.frame_node.items()],
            "frame_offset": [[k, list(v)] for k, v in self.frame_offset.items()],
            "frame_path": [[k, v] for k, v in self.frame_path.items()],
            "turn": self.turn,
            "turn_at_keyframe": self.turn_at_keyframe,
            "familiar": self.familiar,
            "familiar_since": self.familiar_since,
            "sequence_frame": self.sequence_frame,
            "frame_distance": self._frame_distance,
            "frame_turn": self._frame_turn,
            **self._clock_state(),
            "recognitions": self.recognitions,
            "place": self.place,
            "reuse": {
                "base_nodes": self.base_nodes,
                "lost": self.cmap.lost,
                "component_from": self.cmap.component_from,
            },
        }
        arrays["traj"] = self._traj.view
        return pack(meta, arrays)

    @classmethod
    def from_bytes(cls, data: bytes) -> "Mapper":
        """The mapper a snapshot (:meth:`to_bytes`) holds; InputError for anything else."""
        meta, arrays = unpack(data)
        self = cls.__new__(cls)
        self.config = HippomapConfig.model_validate(meta["config"])
        self.pathway = SpatialPathway.from_state(self.config.spatial, join_arrays(meta["pathway"], arrays))
        self.cmap = ReuseMap.from_state(self.config.map, join_arrays(meta["cmap"], arrays))
        reuse = meta.get("reuse") or {}
        self.base_nodes = int(reuse.get("base_nodes", 0))
        self.cmap.configure(self.localise_only, bool(reuse.get("lost", False)), int(reuse.get("component_from", -1)))
        self.memory = VisualMemory.from_state(self.config.visual, join_arrays(meta["memory"], arrays))
        self.last_t = meta["last_t"]
        self.last_odometry_t = meta["last_odometry_t"]
        self.last_frame_t = meta["last_frame_t"]
        self.frames_seen = meta["frames_seen"]
        self.distance = meta["distance"]
        dk = meta["distance_at_keyframe"]
        self.distance_at_keyframe = -math.inf if dk is None else dk
        gs = meta.get("global_search_path")
        self.global_search_path = -math.inf if gs is None else float(gs)
        self.frame_node = {int(k): int(v) for k, v in meta["frame_node"]}
        self.frame_offset = {
            int(k): cast("tuple[float, float, float]", tuple(float(x) for x in v))
            for k, v in meta.get("frame_offset", [])
        }
        self.frame_path = {int(k): float(v) for k, v in meta.get("frame_path", [])}
        self.turn = float(meta.get("turn", 0.0))
        self.turn_at_keyframe = float(meta.get("turn_at_keyframe", 0.0))
        self.familiar = bool(meta.get("familiar", False))
        self.familiar_since = float(meta.get("familiar_since", self.distance))
        sf = meta.get("sequence_frame")
        self.sequence_frame = None if sf is None else int(sf)
        self._frame_distance = float(meta.get("frame_distance", self.distance))
        self._frame_turn = float(meta.get("frame_turn", self.turn))
        self._set_clocks(meta)
        self.recognitions = meta["recognitions"]
        self.place = None if meta["place"] is None else tuple(meta["place"])
        self.place_field = None
        traj = arrays["traj"]
        if traj.shape[1] == _TRAJ_COLUMNS - 1:  # a snapshot from before the time at the node was kept: none
            traj = np.column_stack([traj, np.zeros(len(traj))])
        self._traj = Grow.of(traj)
        return self
