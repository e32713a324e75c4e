"""Ready-made worlds: a rectangular corridor loop, a straight corridor, a figure of eight
of corridors round two blocks, a grid of blocks driven as a random walk, an open hall of
pillars driven as a random walk, an office of rooms off a corridor, and the Bicocca 2009-02-25b
run (real odometry, ground-truth camera path, walls built around it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import wrap_angle
from ..io.datasets import read_g2o, read_groundtruth_csv, read_timestamps
from .motion import RoutePlan, Trajectory
from .params import TextureParams
from .world import World, walls_around_path


def _rect(x0, y0, x1, y1) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]], dtype=float)


def _check_wider(what: str, size: tuple[float, float], corridor_width: float) -> None:
    """Raise :class:`InputError` unless ``size`` (a loop's or a block's sides) exceeds a positive corridor width
    in both directions, so that walls on either side of a corridor never cross."""
    if not (size[0] > corridor_width and size[1] > corridor_width and corridor_width > 0):
        raise InputError(f"{what} {size} must exceed the corridor width {corridor_width} in both directions")


def _wandering(way, closed: bool, laps: int, speed_mps: float, jitter_m: float, seed: int) -> RoutePlan:
    """The route through the waypoints ``way`` driven ``laps`` times at ``speed_mps``, wandering up to about
    ``jitter_m`` beside them, differently each lap and each seed, so that revisits are near, not identical."""
    return RoutePlan(tuple(way), closed=closed, laps=laps, speed_mps=speed_mps, lateral_jitter_m=jitter_m, seed=seed)


def loop_world(
    seed: int = 0,
    size: tuple[float, float] = (16.0, 10.0),
    corridor_width: float = 2.5,
    laps: int = 3,
    speed_mps: float = 0.4,
    texture: TextureParams | None = None,
) -> World:
    """A rectangular corridor loop: the centre line is a ``size`` rectangle with its
    lower-left corner at the origin, walls ``corridor_width / 2`` either side. The
    default route drives it ``laps`` times anticlockwise, starting at (size_x / 2, 0)
    facing +x, each lap wandering slightly so revisits are near, not identical."""
    sx, sy = size
    h = corridor_width / 2
    _check_wider("loop size", size, corridor_width)
    outer = _rect(-h, -h, sx + h, sy + h)
    inner = _rect(h, h, sx - h, sy - h)
    way = [(sx / 2, 0.0), (sx, 0.0), (sx, sy), (0.0, sy), (0.0, 0.0)]
    route = _wandering(way, True, laps, speed_mps, min(0.12, 0.1 * corridor_width), seed)
    return World.from_polylines([outer, inner], name="loop", texture=texture, seed=seed, route=route)


def corridor_world(
    seed: int = 0,
    length: float = 30.0,
    width: float = 2.4,
    passes: int = 2,
    speed_mps: float = 0.4,
    texture: TextureParams | None = None,
) -> World:
    """A straight closed corridor along +x from the origin. The default route drives
    it end to end ``passes`` times (out, back, ...), turning on the spot at each end."""
    h = width / 2
    if not (length > 4 and h > 0.4):
        raise InputError(f"corridor length {length} must be > 4 m and width {width} > 0.8 m")
    walls = _rect(-2.0, -h, length + 2.0, h)
    route = _wandering([(0.0, 0.0), (length, 0.0)], False, passes, speed_mps, min(0.1, 0.1 * width), seed)
    return World.from_polylines([walls], name="corridor", texture=texture, seed=seed, route=route)


def figure8_world(
    seed: int = 0,
    block: tuple[float, float] = (10.0, 7.0),
    corridor_width: float = 2.5,
    laps: int = 3,
    speed_mps: float = 0.4,
    texture: TextureParams | None = None,
) -> World:
    """Corridors round two ``block``-sized blocks side by side, their centre lines the rectangles
    ``[0, bx] x [0, by]`` and ``[bx, 2 bx] x [0, by]``, so the middle corridor is shared and meets
    the others in two T-junctions. The default route drives a figure of eight ``laps`` times,
    starting at (bx / 2, 0) facing +x: round the left block anticlockwise, then up the middle
    corridor again and round the right block clockwise. Junctions are passed in three directions,
    unlike the single loop's corners (walls built round the route, as for Bicocca: :func:`path_world`)."""
    bx, by = block
    _check_wider("figure8 block", block, corridor_width)
    way = [
        (bx / 2, 0.0),
        (bx, 0.0),
        (bx, by),
        (0.0, by),
        (0.0, 0.0),
        (bx, 0.0),
        (bx, by),
        (2 * bx, by),
        (2 * bx, 0.0),
        (bx, 0.0),
    ]
    return _route_world(way, "figure8", True, laps, speed_mps, corridor_width, seed, texture)


def grid_walk(
    seed: int, blocks: tuple[int, int], block: tuple[float, float], length_m: float
) -> list[tuple[float, float]]:
    """Waypoints of a seeded random walk along the lines of a ``blocks`` grid of ``block``-sized blocks
    (junctions ``(i bx, j by)``, ``0 <= i <= nx``, ``0 <= j <= ny``): from ``(bx / 2, 0)`` east to the
    junction ``(bx, 0)``, then at every junction on to a neighbour chosen uniformly among all but the one
    it came from (never straight back), until the walk is at least ``length_m`` long."""
    nx, ny = blocks
    bx, by = block
    rng = np.random.default_rng([seed, 3])
    prev, cur = (0, 0), (1, 0)
    way = [(bx / 2, 0.0), (bx, 0.0)]
    walked = bx / 2
    while walked < length_m:
        i, j = cur
        steps = [(i + di, j + dj) for di, dj in ((1, 0), (0, 1), (-1, 0), (0, -1))]
        steps = [n for n in steps if 0 <= n[0] <= nx and 0 <= n[1] <= ny and n != prev]
        prev, cur = cur, steps[int(rng.integers(len(steps)))]
        way.append((cur[0] * bx, cur[1] * by))
        walked += bx if cur[1] == prev[1] else by
    return way


def grid_world(
    seed: int = 0,
    blocks: tuple[int, int] = (2, 2),
    block: tuple[float, float] = (8.0, 6.0),
    corridor_width: float = 2.5,
    laps: int = 3,
    speed_mps: float = 0.4,
    texture: TextureParams | None = None,
) -> World:
    """Corridors along the lines of a ``blocks`` grid of ``block``-sized blocks (centre lines on
    ``x = i bx``, ``y = j by``): four-way junctions inside, T-junctions on the sides. The default route is
    a random walk over the junctions (:func:`grid_walk`) as long as ``laps`` times the grid's corridors
    together, so, unlike the other worlds' fixed routes, each seed drives its own route, and corridors
    are revisited in both directions after irregular stretches. Walls are built round the walk
    (:func:`path_world`): a corridor the walk never takes is not there."""
    _check_wider("grid block", block, corridor_width)
    way = _lattice_walk(seed, blocks, block, laps, "grid blocks", "grid laps")
    return _route_world(way, "grid", False, 1, speed_mps, corridor_width, seed, texture)


def _lattice_walk(
    seed: int, counts: tuple[int, int], spacing: tuple[float, float], laps: int, counts_name: str, laps_name: str
) -> list[tuple[float, float]]:
    """:func:`grid_walk` over a ``counts`` lattice of ``spacing``-sized squares, ``laps`` times as long as the
    lattice's lines together; :class:`InputError` names ``counts_name`` or ``laps_name`` when either is not a
    positive integer (two for the counts)."""
    nx, ny = counts
    bx, by = spacing
    if not (isinstance(nx, int) and isinstance(ny, int) and nx >= 1 and ny >= 1):
        raise InputError(f"{counts_name} {counts} must be two integers >= 1")
    if not (isinstance(laps, int) and laps >= 1):
        raise InputError(f"{laps_name} {laps!r} must be an integer >= 1")
    network_m = nx * (ny + 1) * bx + (nx + 1) * ny * by
    return grid_walk(seed, (nx, ny), (bx, by), laps * network_m)


def hall_world(
    seed: int = 0,
    lanes: tuple[int, int] = (3, 2),
    spacing: float = 5.0,
    pillar: float = 1.5,
    margin: float = 1.5,
    laps: int = 3,
    speed_mps: float = 0.4,
    texture: TextureParams | None = None,
) -> World:
    """An open hall: one room whose floor is a ``lanes`` grid of ``spacing``-metre squares, a square pillar
    ``pillar`` metres wide at the centre of each, and the hall's walls ``margin`` beyond the outer lanes. The
    default route is a random walk along the lanes between the pillars (:func:`grid_walk`) as long as ``laps``
    times the lanes together. Unlike the corridor worlds, nothing walls a lane in: the camera sees across the
    hall, past the pillars (their faces 1.75 m beside each lane by default) to walls up to about 20 m away, and a
    place is passed again from any side."""
    if not (0 < pillar < spacing - 1.0):
        raise InputError(f"hall pillar {pillar} must be positive and leave more than 1 m of lane ({spacing} m apart)")
    if not margin > 0.5:
        raise InputError(f"hall margin {margin} must leave more than 0.5 m between the outer lanes and the walls")
    way = _lattice_walk(seed, lanes, (spacing, spacing), laps, "hall lanes", "hall laps")
    nx, ny = lanes
    sx, sy = nx * spacing, ny * spacing
    polys = [_rect(-margin, -margin, sx + margin, sy + margin)]
    h = pillar / 2
    for i in range(nx):
        for j in range(ny):
            cx, cy = (i + 0.5) * spacing, (j + 0.5) * spacing
            polys.append(_rect(cx - h, cy - h, cx + h, cy + h))
    route = _wandering(way, False, 1, speed_mps, 0.12, seed)
    return World.from_polylines(polys, name="hall", texture=texture, seed=seed, route=route)


#: the office world's rooms: (centre x along the corridor, side: +1 north, -1 south)
OFFICE_ROOMS = ((4.0, 1), (9.0, -1), (14.0, 1), (19.0, -1), (24.0, 1))


def _office_room(xc: float, side: int, half_width: float, room: tuple[float, float], desk: tuple[float, float]):
    """One room of :func:`office_world`: its three walls beyond the corridor's (an open polyline), its desk (a
    closed one), and the waypoints of a visit from the corridor's centre line: through the door, once round
    the desk anticlockwise (seen from above), back out through the door."""
    rw, rd = room
    y0, y1 = side * half_width, side * (half_width + rd)
    walls = np.array([[xc - rw / 2, y0], [xc - rw / 2, y1], [xc + rw / 2, y1], [xc + rw / 2, y0]])
    ym = side * (half_width + rd / 2)
    dx, dy = desk[0] / 2, desk[1] / 2
    desk_poly = _rect(xc - dx, ym - dy, xc + dx, ym + dy)
    near, far = side * (half_width + 0.9), side * (half_width + rd - 0.9)
    ax, bx = xc - rw / 2 + 0.9, xc + rw / 2 - 0.9
    ring = [(xc, near), (bx, near), (bx, far), (ax, far), (ax, near), (xc, near)]
    if side < 0:  # the near side is the desk's north here: anticlockwise starts westwards
        ring = [(xc, near), (ax, near), (ax, far), (bx, far), (bx, near), (xc, near)]
    return walls, desk_poly, [(xc, 0.0)] + ring + [(xc, 0.0)]


def office_world(
    seed: int = 0,
    length: float = 28.0,
    corridor_width: float = 2.4,
    room: tuple[float, float] = (5.0, 5.0),
    door: float = 1.6,
    desk: tuple[float, float] = (1.6, 1.2),
    passes: int = 3,
    speed_mps: float = 0.4,
    texture: TextureParams | None = None,
) -> World:
    """An office: a straight corridor along +x from the origin, ``length`` long and ``corridor_width`` wide,
    closed at both ends, with five ``room``-sized rooms (width along the corridor, depth) off it, three on the
    north side and two on the south (:data:`OFFICE_ROOMS`), each entered through a ``door`` in the corridor's
    wall and holding a ``desk`` at its centre. The default route drives the corridor end to end ``passes`` times
    (out, back, ...), and on each pass visits each room it passes with even odds (the seed's; at least one per
    pass): in through the door, once round the desk, out again. Rooms visited on several passes are revisited
    from the same side; the corridor is revisited in both directions. Unlike the other worlds, a revisit often
    starts in a doorway, after a sharp turn out of a small room."""
    h = corridor_width / 2
    rw, rd = room
    if not (length >= 26.0 and 1.6 <= corridor_width and 4.0 <= rw <= 10.0 and rd >= 4.0):
        raise InputError(
            f"office length {length} must be >= 26 m, corridor width {corridor_width} >= 1.6 m and rooms {room} "
            "4-10 m wide and at least 4 m deep (the rooms of a side are 10 m apart, and a visit circles the desk)"
        )
    if not (1.2 <= door < rw - 1.0 and 0 < desk[0] < rw - 3.2 and 0 < desk[1] < rd - 3.2):
        raise InputError(f"office door {door} must be 1.2 m to {rw - 1.0} m wide and desk {desk} leave 1.6 m round it")
    if not (isinstance(passes, int) and passes >= 1):
        raise InputError(f"office passes {passes!r} must be an integer >= 1")
    polys, visits = [], {}
    for xc, side in OFFICE_ROOMS:
        walls, desk_poly, visit = _office_room(xc, side, h, room, desk)
        polys += [walls, desk_poly]
        visits[(xc, side)] = visit
    for side in (1, -1):  # the corridor's walls, with a gap for each door on that side
        doors = sorted(xc for xc, s in OFFICE_ROOMS if s == side)
        xs = [-1.5] + [x for xc in doors for x in (xc - door / 2, xc + door / 2)] + [length + 1.5]
        polys += [np.array([[xs[i], side * h], [xs[i + 1], side * h]]) for i in range(0, len(xs), 2)]
    polys.append(np.array([[-1.5, -h], [-1.5, h]]))
    polys.append(np.array([[length + 1.5, -h], [length + 1.5, h]]))
    rng = np.random.default_rng([seed, 5])
    way: list[tuple[float, float]] = [(0.0, 0.0)]
    for k in range(passes):
        order = sorted(OFFICE_ROOMS, reverse=bool(k % 2))
        go = rng.random(len(order)) < 0.5
        if not go.any():
            go[int(rng.integers(len(order)))] = True
        for (xc, side), g in zip(order, go):
            if g:
                way += visits[(xc, side)]
        way.append((length if k % 2 == 0 else 0.0, 0.0))
    route = _wandering(way, False, 1, speed_mps, 0.1, seed)
    return World.from_polylines(polys, name="office", texture=texture, seed=seed, route=route)


def _route_world(
    way: list[tuple[float, float]],
    name: str,
    closed: bool,
    laps: int,
    speed_mps: float,
    corridor_width: float,
    seed: int,
    texture: TextureParams | None,
) -> World:
    """A corridor ``corridor_width`` wide round the waypoints ``way`` (walls by :func:`path_world` round the
    centre line), with the route along them as the world's default, wandering a little each lap."""
    route = _wandering(way, closed, laps, speed_mps, min(0.12, 0.1 * corridor_width), seed)
    centre = RoutePlan(tuple(way), closed=closed, lateral_jitter_m=0.0).path(0.05)
    return path_world(centre, half_width_m=corridor_width / 2, seed=seed, texture=texture, route=route, name=name)


def interpolate_poses(t_query, t, poses) -> np.ndarray:
    """Poses (M, 3) at times ``t`` linearly interpolated at ``t_query`` (headings
    through their unwrapped values). Times outside [t0, t_end] are clamped."""
    th = np.unwrap(poses[:, 2])
    out = np.stack(
        [np.interp(t_query, t, poses[:, 0]), np.interp(t_query, t, poses[:, 1]), wrap_angle(np.interp(t_query, t, th))],
        axis=1,
    )
    return out


def bicocca_trajectory(data_dir: str | Path, g2o: str = "B25b_1.000.g2o") -> Trajectory:
    """The Bicocca 25b run: the g2o file's odometry edges as measured odometry; the
    ground-truth CSV matched by timestamp (linear interpolation at the odometry times)
    as the camera path; odometry poses outside the ground truth's time span dropped."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise InputError(f"Bicocca folder {data_dir} does not exist")
    graph = read_g2o(data_dir / g2o)
    stamps = sorted(data_dir.glob("*timestamps.txt"))
    gts = sorted(data_dir.glob("*GT*.csv"))
    if not stamps or not gts:
        raise InputError(f"{data_dir} needs a *timestamps.txt and a *GT*.csv file")
    times = read_timestamps(stamps[0])
    if len(times) != len(graph.vertices):
        raise InputError(f"{stamps[0]} has {len(times)} timestamps for {len(graph.vertices)} poses in {g2o}")
    gt_t, gt = read_groundtruth_csv(gts[0])
    keep = np.flatnonzero((times >= gt_t[0]) & (times <= gt_t[-1]))
    if len(keep) < 2:
        raise InputError(f"odometry times and ground-truth times of {data_dir} do not overlap")
    a, b = int(keep[0]), int(keep[-1]) + 1
    poses = interpolate_poses(times[a:b], gt_t, gt)
    return Trajectory(times[a:b], poses, odometry=graph.odometry[a : b - 1])


def bicocca_world(
    data_dir: str | Path = "../shared/data/bicocca25b",
    g2o: str = "B25b_1.000.g2o",
    seed: int = 0,
    half_width_m: float = 1.2,
    resolution_m: float = 0.1,
    texture: TextureParams | None = None,
) -> World:
    """Walls around the Bicocca ground-truth path (:func:`walls_around_path`: free space
    = within ``half_width_m`` of the path) and the real run as the default route."""
    traj = bicocca_trajectory(data_dir, g2o)
    polys = walls_around_path(traj.poses[:, :2], half_width_m=half_width_m, resolution_m=resolution_m)
    return World.from_polylines(polys, name="bicocca25b", texture=texture, seed=seed, route=traj)


def path_world(
    path_xy,
    *,
    half_width_m: float = 1.2,
    resolution_m: float = 0.1,
    seed: int = 0,
    texture: TextureParams | None = None,
    route=None,
    name: str = "path",
) -> World:
    """Walls around any 2-D path (as for Bicocca), e.g. a synthetic one."""
    polys = walls_around_path(path_xy, half_width_m=half_width_m, resolution_m=resolution_m)
    return World.from_polylines(polys, name=name, texture=texture, seed=seed, route=route)
