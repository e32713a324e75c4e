"""Frozen parameter sets of the camera simulator.

These are *simulator* parameters (the world the robot is put in), not model parameters:
they deliberately live here and not in ``hippomap/config.py``. Every dataclass is frozen
and validates on construction, raising :class:`~hippomap.errors.InputError` naming the
bad field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

from ..errors import InputError


def _check(obj, name: str, ok: bool, what: str) -> None:
    if not ok:
        raise InputError(f"{type(obj).__name__}.{name} = {getattr(obj, name)!r}: {what}")


def _finite(obj) -> None:
    for f in fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            raise InputError(f"{type(obj).__name__}.{f.name} = {v!r}: must be finite")


@dataclass(frozen=True)
class Camera:
    """Pinhole camera on the robot, looking along the robot's heading.

    Square pixels, principal point at the image centre, so the focal length in pixels is
    ``f = (width / 2) / tan(hfov / 2)`` and a wall of height ``H`` at forward depth ``d``
    projects to ``f * H / d`` rows. Defaults: 320x240 (the spec's frame size, §2), 60°
    horizontal field of view, lens 0.5 m above the floor (Turtlebot-2 class robot, as in
    the paper's own experiment).
    """

    width: int = 320
    height: int = 240
    hfov_deg: float = 60.0
    mount_height_m: float = 0.5
    max_range_m: float = 80.0
    #: first ray-casting pass only looks at walls within this radius (large worlds);
    #: columns that hit nothing that close are cast again against everything in range.
    near_range_m: float = 12.0
    #: grey-level std of per-pixel sensor noise added to simulated frames (seeded per
    #: frame, so a run stays deterministic); 0 renders noise-free images
    pixel_noise: float = 0.0
    #: the scene's light changing slowly (clouds, lamps, the camera's auto-exposure): frame grey levels
    #: are scaled by ``1 + exposure_change * sin(2 pi t / exposure_period_s)`` (clipped at white), so a
    #: place seen again on a later lap can be brighter or darker than when it was learned; 0 = constant
    exposure_change: float = 0.0
    #: seconds of one brightness cycle; not a multiple of a lap, so revisits meet other light
    exposure_period_s: float = 97.0

    def __post_init__(self):
        _finite(self)
        _check(self, "width", isinstance(self.width, int) and 8 <= self.width <= 8192, "integer in [8, 8192]")
        _check(self, "height", isinstance(self.height, int) and 8 <= self.height <= 8192, "integer in [8, 8192]")
        _check(self, "hfov_deg", 1.0 <= self.hfov_deg <= 170.0, "horizontal field of view in [1, 170] degrees")
        _check(self, "mount_height_m", self.mount_height_m > 0, "must be > 0")
        _check(self, "max_range_m", self.max_range_m > 0, "must be > 0")
        _check(self, "near_range_m", self.near_range_m > 0, "must be > 0")
        _check(self, "pixel_noise", self.pixel_noise >= 0, "must be >= 0")
        _check(self, "exposure_change", 0 <= self.exposure_change < 1, "a fraction in [0, 1)")
        _check(self, "exposure_period_s", self.exposure_period_s > 0, "must be > 0")

    def exposure_gain(self, t: float) -> float:
        """The factor on the frame's grey levels at time ``t`` (s): 1 without ``exposure_change``."""
        if self.exposure_change == 0:
            return 1.0
        return 1.0 + self.exposure_change * math.sin(2 * math.pi * t / self.exposure_period_s)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (both axes)."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def cx(self) -> float:
        return 0.5 * self.width

    @property
    def cy(self) -> float:
        return 0.5 * self.height

    @property
    def K(self):
        """3x3 intrinsic matrix (pixel centres at integer + 0.5)."""
        import numpy as np

        f = self.focal_px
        return np.array([[f, 0.0, self.cx], [0.0, f, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Shading:
    """How walls, floor and ceiling are lit. View-consistent by default (a place looks the same
    every time it is seen from the same pose); with ``light_swing_deg`` the light's direction
    changes with time (:meth:`at`), so walls facing it brighten while the others darken."""

    #: wall brightness falls as 1 / (1 + depth / fog_m) towards ``fog_floor`` of its value
    fog_m: float = 12.0
    fog_floor: float = 0.35
    #: walls facing different directions get different brightness (light from ``light_deg``,
    #: a wall's brightness between 1 - directional and 1 as it faces away from or towards it)
    light_deg: float = 30.0
    directional: float = 0.25
    #: the light's direction swings by up to this much about ``light_deg`` (lamps switched, the
    #: sun moving): ``light_deg + light_swing_deg * sin(2 pi t / light_period_s)`` at time t
    light_swing_deg: float = 0.0
    #: seconds of one swing (not a multiple of a lap: revisits meet the light from elsewhere)
    light_period_s: float = 131.0
    floor_level: float = 95.0
    ceiling_level: float = 185.0
    #: world-anchored floor tiles with a seeded shade each; contrast fades with distance
    floor_tile_m: float = 0.6
    floor_contrast: float = 10.0
    floor_fade_m: float = 4.0

    def __post_init__(self):
        _finite(self)
        _check(self, "fog_m", self.fog_m > 0, "must be > 0")
        _check(self, "fog_floor", 0 <= self.fog_floor <= 1, "in [0, 1]")
        _check(self, "directional", 0 <= self.directional < 1, "in [0, 1)")
        _check(self, "floor_level", 0 <= self.floor_level <= 255, "grey level in [0, 255]")
        _check(self, "ceiling_level", 0 <= self.ceiling_level <= 255, "grey level in [0, 255]")
        _check(self, "floor_tile_m", self.floor_tile_m > 0, "must be > 0")
        _check(self, "floor_contrast", self.floor_contrast >= 0, "must be >= 0")
        _check(self, "floor_fade_m", self.floor_fade_m > 0, "must be > 0")
        _check(self, "light_swing_deg", 0 <= self.light_swing_deg <= 180, "degrees in [0, 180]")
        _check(self, "light_period_s", self.light_period_s > 0, "must be > 0")

    def at(self, t: float) -> "Shading":
        """The shading at time ``t`` (s): the light turned by its swing (this shading without one)."""
        if self.light_swing_deg == 0:
            return self
        turn = self.light_swing_deg * math.sin(2 * math.pi * t / self.light_period_s)
        return replace(self, light_deg=self.light_deg + turn)


@dataclass(frozen=True)
class TextureParams:
    """Wall appearance. ``source`` is ``"procedural"`` (seeded, never repeating) or a
    folder of photos (``*.jpg``, ``*.jpeg``, ``*.png``) laid along the walls."""

    source: str = "procedural"
    wall_height_m: float = 2.5
    #: texture resolution on the wall (texels per metre, both directions)
    texels_per_m: float = 48.0
    #: mean spacing of posters / notices / doors along a wall (procedural textures)
    feature_spacing_m: float = 0.6
    #: photo textures: overlay procedural posters on the photos so that repeated photos
    #: (when walls are longer than the photo set) still give distinct places
    photo_overlay: bool = True
    #: photo textures: use only the first this many photos of the folder (sorted by name; None = all).
    #: Fewer photos repeat more often along the walls: without the overlay, distant places look alike
    photo_count: int | None = None

    def __post_init__(self):
        _finite(self)
        _check(self, "wall_height_m", self.wall_height_m > 0, "must be > 0")
        _check(self, "texels_per_m", 4 <= self.texels_per_m <= 1000, "in [4, 1000]")
        _check(self, "feature_spacing_m", self.feature_spacing_m > 0, "must be > 0")
        _check(self, "photo_count", self.photo_count is None or self.photo_count >= 1, "must be >= 1 or None")

    @property
    def rows(self) -> int:
        """Texture rows spanning the wall height."""
        return max(8, int(round(self.wall_height_m * self.texels_per_m)))


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel-odometry error model applied to the true (v, ω) of every step:

    ``v_meas = (1 + scale_error) * v + N(0, sigma_v)``,
    ``ω_meas = ω + b(t) + N(0, sigma_omega)``, ``b(t) = omega_bias + W(t)``.

    A constant ``omega_bias`` makes the integrated heading drift by ``omega_bias * T``;
    ``scale_error`` stretches every distance by ``1 + scale_error``. ``omega_bias_walk`` lets the
    bias itself wander as a real gyro's does (temperature, bias instability): ``W`` is a random walk
    whose steps over ``dt`` seconds are ``N(0, omega_bias_walk * sqrt(dt))`` ((rad/s)/√s, a gyro
    data sheet's rate random walk), so after ``T`` seconds the bias has moved by about
    ``omega_bias_walk * sqrt(T)``; 0 keeps it constant.

    A field left out is 0, so ``OdometryNoise()`` is exact odometry and
    ``OdometryNoise(omega_bias=0.01)`` a pure heading drift. :meth:`realistic` is the wheel
    odometry a simulated run gets when it names no noise (:class:`SimConfig`'s default).
    """

    sigma_v: float = 0.0  # m/s
    sigma_omega: float = 0.0  # rad/s
    omega_bias: float = 0.0  # rad/s
    scale_error: float = 0.0  # fraction
    omega_bias_walk: float = 0.0  # (rad/s)/sqrt(s)

    def __post_init__(self):
        _finite(self)
        _check(self, "sigma_v", self.sigma_v >= 0, "must be >= 0")
        _check(self, "sigma_omega", self.sigma_omega >= 0, "must be >= 0")
        _check(self, "scale_error", self.scale_error > -1, "must be > -1")
        _check(self, "omega_bias_walk", self.omega_bias_walk >= 0, "must be >= 0")

    @classmethod
    def realistic(cls) -> "OdometryNoise":
        """Realistic wheel odometry, the set the README and the map benchmarks use: speed
        noise 0.02 m/s, turn-rate noise 0.01 rad/s and a turn-rate bias of 0.01 rad/s (the
        heading drifts by about 0.6 degrees a second). Without noise a simulated run's
        odometry is its ground truth, and there is no drift for the map to correct."""
        return cls(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)

    @property
    def is_zero(self) -> bool:
        return (
            self.sigma_v == 0
            and self.sigma_omega == 0
            and self.omega_bias == 0
            and self.scale_error == 0
            and self.omega_bias_walk == 0
        )


@dataclass(frozen=True)
class SimConfig:
    """Everything :func:`hippomap.sim.simulate` needs besides the world and the path.

    ``rate_hz`` is the odometry rate used to sample drive plans (5 Hz, the paper's 0.2 s
    sampling period); a given :class:`~hippomap.sim.motion.Trajectory` keeps its own
    times. A camera frame is rendered every ``frame_every`` odometry steps. With
    ``stop_every_m`` > 0 the robot stands still for ``stop_s`` seconds each time it has
    driven that much further (:func:`~hippomap.sim.motion.with_stops`).
    """

    camera: Camera = field(default_factory=Camera)
    shading: Shading = field(default_factory=Shading)
    #: realistic by default; ``OdometryNoise()`` for exact odometry
    odometry_noise: OdometryNoise = field(default_factory=OdometryNoise.realistic)
    rate_hz: float = 5.0
    frame_every: int = 1
    seed: int = 0
    image_format: str = "png"
    stop_every_m: float = 0.0
    stop_s: float = 0.0

    def __post_init__(self):
        _finite(self)
        for name, cls in (("camera", Camera), ("shading", Shading), ("odometry_noise", OdometryNoise)):
            _check(self, name, isinstance(getattr(self, name), cls), f"must be a {cls.__name__}")
        _check(self, "rate_hz", self.rate_hz > 0, "must be > 0")
        _check(self, "frame_every", isinstance(self.frame_every, int) and self.frame_every >= 1, "integer >= 1")
        _check(self, "seed", isinstance(self.seed, int), "must be an integer")
        _check(self, "image_format", self.image_format in ("png", "jpg"), "'png' or 'jpg'")
        _check(self, "stop_every_m", self.stop_every_m >= 0, "must be >= 0 (0: no stops)")
        _check(self, "stop_s", self.stop_s > 0 or self.stop_every_m == 0, "must be > 0 when the robot stops")
