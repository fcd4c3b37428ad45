"""Scenario schema: the YAML a user runs, validated with pydantic.

Every model forbids unknown keys. :func:`load_scenario` turns pydantic's errors into
:class:`ScenarioError` whose lines name the dotted key path, the offending value and
what is allowed. ``--set dotted.key=value`` overrides are applied to the raw YAML
before validation, so they are checked like everything else. Files and override values
are read by :func:`sim.safe_yaml.load` (safe, bounded, no duplicate keys); numbers are
strict and finite, and plausibility bounds say why (``json_schema_extra={"why": ...}``).

Robot presets follow thesis 7.1 (LRU narrow stereo 50.6 deg, b = 9 cm; wide-angle
112.8 deg; ARDEA two stereo pairs b = 12 cm tilted +-60 deg). Default lane stage costs
come from the on-board measurements of thesis 8.4.
"""

from __future__ import annotations

import copy
import inspect
import itertools
import math
import typing
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from comms import CommsConfig, CommsError
from comms.config import StrictConfig
from sim import safe_yaml
from sim.robots import PRESETS
from sim.world.lander import LANDER_PAD_RADIUS, LANDER_RADIUS
from slam.agent import MESSAGE_KINDS, AgentParams
from slam.filter import FilterParams
from slam.graph import GraphParams
from slam.health import HealthParams
from slam.local_estimator import LocalEstimator
from slam.matcher import MatcherParams
from slam.navigation.exploration import ExplorationParams
from slam.obstacles import ObstacleParams
from slam.rest import RestParams
from slam.submap import SubmapParams
from slam.vo import VoParams

NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_]{0,31}$"

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
XY = tuple[float, float]
# Plausibility bounds; ``why`` (in the JSON schema) is what an error message adds.
RockDiameter = Annotated[float, Field(gt=0, le=3, json_schema_extra={"why": "larger relief is craters and ridges; every rock fits on 5 m"})]
Altitude = Annotated[float, Field(gt=0, le=100, json_schema_extra={"why": "the hexacopter's stereo sees the ground to about 10 m"})]

#: Heights per side of the terrain grid: 4097^2 float64 heights are 134 MB, and generating
#: them holds several such arrays; MuJoCo's hfield and the renderer get slow long before.
MAX_GRID_POINTS = 4097
#: Samples of the link time series (``duration_s / comms.stats_interval_s``): each keeps
#: about 50 bytes per link, so 200,000 are 120 MB with four nodes (12 links).
MAX_LINK_SAMPLES = 200_000
#: Keep-clear discs along the routes (:meth:`Scenario.keep_clear`): the terrain generator
#: tests every rock candidate against each of them.
MAX_KEEP_CLEAR_DISCS = 10_000


class ScenarioError(ValueError):
    """A scenario that cannot be loaded; ``problems`` holds one readable line each."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        super().__init__(f"{source}: invalid scenario\n  " + "\n  ".join(problems))


class StrictModel(StrictConfig):
    """Base of every scenario section: unknown keys, NaN, infinities and numbers of the
    wrong type are errors (:class:`comms.config.StrictConfig`); assignments are validated too."""

    model_config = ConfigDict(validate_assignment=True)


def _ordered_range(value: tuple[float, float], what: str) -> tuple[float, float]:
    if value[0] > value[1]:
        raise ValueError(f"{what} must be [min, max] with min <= max")
    return value


# --------------------------------------------------------------------------- keys that set slam parameters


@dataclass(frozen=True)
class SlamParam:
    """The parameter ``name`` of ``target`` (a slam parameter dataclass or function) that
    a scenario key sets; ``degrees``: the key takes degrees, the parameter radians."""

    target: Callable[..., Any]
    name: str
    degrees: bool = False

    @property
    def slam_default(self) -> Any:
        """The parameter's default in slam (``inspect.Parameter.empty`` if it has none)."""
        return inspect.signature(self.target).parameters[self.name].default

    def key_default(self) -> Any:
        """The slam default in the scenario key's units (enums by value)."""
        value = self.slam_default
        if value is inspect.Parameter.empty:
            return value
        if isinstance(value, Enum):
            return value.value
        if not self.degrees:
            return value
        deg = round(math.degrees(value), 9)
        if math.radians(deg) != value:
            raise TypeError(f"{self}: the default {value!r} rad is no round number of degrees")
        return deg

    def to_slam(self, value: Any) -> Any:
        """A scenario value as the slam parameter takes it."""
        if self.degrees:
            return math.radians(value)
        default = self.slam_default
        return type(default)(value) if isinstance(default, Enum) else value


def slam_field(*params: SlamParam, default: Any = inspect.Parameter.empty, **kwargs: Any) -> Any:
    """A pydantic field for a key that sets the slam ``params``; its default is theirs
    (they must agree), so slam's parameter classes are the one source of defaults.
    ``default`` only for parameters without one in slam. :func:`slam_kwargs` reads the
    link back."""
    defaults = {p.key_default() for p in params}
    if len(defaults) != 1:
        raise TypeError(f"slam parameters {params} have different defaults: {defaults}")
    (own,) = defaults
    if (own is inspect.Parameter.empty) == (default is inspect.Parameter.empty):
        raise TypeError(f"{params}: give a default exactly when slam has none")
    info = Field(default if own is inspect.Parameter.empty else own, **kwargs)
    info.metadata.extend(params)
    return info


def slam_kwargs(target: Callable[..., Any], *sections: BaseModel) -> dict[str, Any]:
    """Keyword arguments for ``target`` from the scenario ``sections`` whose keys set its
    parameters (declared with :func:`slam_field`)."""
    out = {}
    for section in sections:
        for key, info in type(section).model_fields.items():
            for param in info.metadata:
                if isinstance(param, SlamParam) and param.target is target:
                    out[param.name] = param.to_slam(getattr(section, key))
    return out


# --------------------------------------------------------------------------- terrain


class CraterConfig(StrictModel):
    """Bowl-shaped craters with raised rims (depth and rim height relative to radius)."""

    count: int = Field(6, ge=0, le=500, description="number of craters (no centre inside a keep-clear disc)")
    radius_m: tuple[PositiveFloat, PositiveFloat] = Field((1.0, 4.0), description="[min, max] of the rim crest radius, drawn uniformly")
    depth_ratio: float = Field(0.2, gt=0, le=1.0, description="depth / radius")
    rim_height_ratio: float = Field(0.06, ge=0, le=0.5, description="rim height / radius")

    _range = field_validator("radius_m")(lambda v: _ordered_range(v, "radius_m"))


class SlopeConfig(StrictModel):
    """A global planar tilt of the heightfield."""

    gradient_deg: float = Field(0.0, ge=0, le=30, description="inclination of the tilted plane (0: level)")
    direction_deg: float = Field(0.0, description="direction in which the ground rises, counter-clockwise from +x")


class RidgeConfig(StrictModel):
    """A straight ridge (positive height) or trench/ramp cut (negative height)."""

    start_xy: XY = Field(..., description="[x, y] of one end of the centre line (m, origin at the terrain centre)")
    end_xy: XY = Field(..., description="[x, y] of the other end of the centre line (m)")
    height_m: float = Field(..., ge=-5, le=5, description="crest height (negative: a trench or ramp cut)")
    width_m: PositiveFloat = Field(2.0, description="full width of the cos^2 cross-section")


#: A rock's horizontal reach is at most this times half its diameter (the radial jitter of its shape, sim/world/terrain.py).
ROCK_MAX_REACH_FACTOR = 1.15


class PlacedRockConfig(StrictModel):
    xy: XY = Field(..., description="centre of the rock (m, origin at the terrain centre)")
    diameter_m: RockDiameter = Field(..., description="longest horizontal extent; the shape is drawn like the random rocks'")


class RockConfig(StrictModel):
    """Rocks as separate geoms; diameters follow a truncated power law
    N(>D) ~ D^-exponent, the usual model of planetary rock size-frequency."""

    placed: list[PlacedRockConfig] = Field(
        [],
        max_length=100,
        description="rocks exactly where given (e.g. in a robot's way), besides the `count` random ones; only robot starts and the lander stay clear",
    )
    count: int = Field(25, ge=0, le=2000, description="number of rocks")
    diameter_m: tuple[RockDiameter, RockDiameter] = Field((0.15, 0.8), description="[min, max] diameter of the truncated power law")
    power_law_exponent: float = Field(2.5, gt=0, le=6, description="k of N(>D) ~ D^-k: larger makes small rocks more frequent")
    clearance_m: float = Field(
        2.0,
        ge=0.1,
        description="keep rocks this far from robot starts, waypoints' straight legs and the lander",
        json_schema_extra={"why": "the legs are kept clear by discs every clearance_m along them: a tiny one makes millions"},
    )

    _range = field_validator("diameter_m")(lambda v: _ordered_range(v, "diameter_m"))


class LanderConfig(StrictModel):
    xy: XY = Field((0.0, 0.0), description="centre of the lander (m, origin at the terrain centre)")
    yaw_deg: float = Field(0.0, description="heading of the lander, counter-clockwise from +x; its tag faces along the lander's +x")
    tag_id: int = Field(0, ge=0, le=586, description="AprilTag 36h11 id of the lander's marker")
    tag_size_m: PositiveFloat = Field(0.4, description="edge of the tag's black square")


class TextureConfig(StrictModel):
    """Procedural regolith albedo: multi-octave noise from the seed."""

    size_px: int = Field(2048, ge=256, le=8192, description="side of the square, tileable albedo texture in texels; it repeats to cover the terrain")
    texel_m: float = Field(
        0.02, ge=0.001, le=1.0, description="ground size of one texel", json_schema_extra={"why": "cameras see no finer, SGBM matches no coarser"}
    )
    contrast: float = Field(0.35, gt=0, le=1.0, description="std of the albedo relative to its mean")


class TerrainConfig(StrictModel):
    preset: Literal["moon", "mars", "etna"] = Field("moon", description="site look: albedo, colours, sun and sky (etna also 2.5 x roughness_m)")
    size_m: float = Field(40.0, ge=5, le=500, description="side length of the square terrain")
    resolution_m: float = Field(0.1, ge=0.02, le=1.0, description="heightfield grid spacing")
    roughness_m: float = Field(
        0.05, ge=0, le=2, description="amplitude of fractal surface noise", json_schema_extra={"why": "larger relief: craters, ridges, slope"}
    )
    roughness_wavelength_m: PositiveFloat = Field(
        4.0, description="longest wavelength of the fractal roughness; octaves halve down to two grid cells"
    )
    craters: CraterConfig = Field(CraterConfig(), description="bowl-shaped craters with raised rims")
    slope: SlopeConfig = Field(SlopeConfig(), description="a global planar tilt of the terrain")
    ridges: list[RidgeConfig] = Field([], description="straight ridges or trenches (none by default)")
    rocks: RockConfig = Field(RockConfig(), description="rocks as separate geoms, kept off the robots' starts and routes")
    lander: LanderConfig | None = Field(
        None, description="a lander on a flattened pad with an AprilTag, a static landmark (thesis 6.2); null: no lander"
    )
    texture: TextureConfig = Field(TextureConfig(), description="procedural regolith albedo texture")

    def grid_points(self) -> int:
        """Heights per side of the terrain grid."""
        return max(2, round(self.size_m / self.resolution_m)) + 1

    def lander_keep_clear(self) -> list[tuple[XY, float]]:
        """The disc ``(xy, radius)`` around the lander that rocks and crater centres keep out of (none without a lander)."""
        return [] if self.lander is None else [(self.lander.xy, LANDER_RADIUS + self.rocks.clearance_m)]

    @model_validator(mode="after")
    def _check_fits(self) -> TerrainConfig:
        n = self.grid_points()
        if n > MAX_GRID_POINTS:
            raise ValueError(
                f"size_m={self.size_m:g} at resolution_m={self.resolution_m:g} is {n - 1} cells per side: the heightfield "
                f"would hold {n}x{n} heights ({n * n * 8 / 1e9:.1f} GB, several times that while it is generated); at most "
                f"{MAX_GRID_POINTS - 1} cells per side: raise resolution_m to >= {self.size_m / (MAX_GRID_POINTS - 1):.3g}"
            )
        if self.roughness_wavelength_m < 2 * self.resolution_m:
            raise ValueError(
                f"roughness_wavelength_m={self.roughness_wavelength_m:g} is shorter than two grid cells "
                f"(2 x resolution_m = {2 * self.resolution_m:g} m): the grid cannot hold it"
            )
        if self.lander is not None and max(map(abs, self.lander.xy)) > self.size_m / 2 - LANDER_PAD_RADIUS:
            raise ValueError(
                f"lander.xy={list(self.lander.xy)} must lie within {self.size_m / 2 - LANDER_PAD_RADIUS:g} m "
                f"of the centre in x and y (its pad is {LANDER_PAD_RADIUS:g} m in radius, size_m={self.size_m:g})"
            )
        return self


# --------------------------------------------------------------------------- robots


def _per_preset(attribute: str) -> str:
    """A robot class attribute for every preset, e.g. ``lru 4, lru_wide 4, ardea 2`` (tuples as ``a/b``, empty: none)."""

    def shown(value: Any) -> str:
        return "/".join(map(str, value)) or "none" if isinstance(value, tuple) else str(value)

    return ", ".join(f"{name} {shown(getattr(robot, attribute))}" for name, robot in PRESETS.items())


class CameraConfig(StrictModel):
    """Rendered rectified pinhole stereo. ``hfov_deg`` overrides the preset's."""

    width: int = Field(320, ge=32, le=2048, description="image width (px)")
    height: int = Field(240, ge=32, le=2048, description="image height (px)")
    rate_hz: float = Field(5.0, gt=0, le=30, description="stereo frame rate; must divide physics.control_rate_hz (thesis 7.1: 8 to 14.6 Hz)")
    trigger_phase: float | None = Field(
        None,
        ge=0,
        lt=1,
        description=(
            "when in each frame period the robot's cameras trigger, as a fraction of the period "
            "(null: robot k of a team of n at k/n: the cameras of separate robots run free, and the image pipeline's work is spread)"
        ),
    )
    color: Literal["grey", "rgb"] = Field("grey", description="rendered images: grey (one channel, as the thesis's rovers, 7.1) or rgb")
    hfov_deg: float | None = Field(
        None, gt=10, lt=170, description=f"horizontal field of view (null: the preset's, {_per_preset('default_hfov_deg')})"
    )
    depth_ground_truth_every: int = Field(
        1, ge=0, description="render ground-truth depth every n-th frame (0: never)"
    )
    flat_field: bool = Field(
        True,
        description=(
            "the camera pipeline divides each image by the lens's calibrated relative illumination (flat-field correction of "
            "realism.camera.vignetting) before stereo, VO and detection; false: the images keep their vignetting"
        ),
    )
    znear_m: PositiveFloat = Field(0.05, description="near clipping plane of the renderer")
    zfar_m: PositiveFloat = Field(60.0, description="far clipping plane; ground-truth depth beyond it is inf")

    @model_validator(mode="after")
    def _check_clipping(self) -> CameraConfig:
        if self.znear_m >= self.zfar_m:
            raise ValueError(f"znear_m ({self.znear_m:g}) must be less than zfar_m ({self.zfar_m:g})")
        return self


class ImuConfig(StrictModel):
    preset: Literal["xsens_mti10", "adis16407"] | None = Field(
        None, description=f"default per preset: {_per_preset('default_imu_preset')} (thesis 7.1)"
    )
    rate_hz: float = Field(200.0, gt=0, le=1000, description="IMU sample rate; must divide physics.control_rate_hz")


class WheelOdometryConfig(StrictModel):
    rate_hz: float = Field(50.0, gt=0, le=500, description="wheel odometry sample rate; must divide physics.control_rate_hz")
    speed_noise_std_mps: NonNegFloat = Field(0.01, description="white noise std on the body velocities v_x and v_y")
    yaw_rate_noise_std_rps: NonNegFloat = Field(0.01, description="white noise std on the yaw rate (rad/s)")


class WaypointConfig(StrictModel):
    xy: XY = Field(..., description="waypoint position (m, origin at the terrain centre)")
    altitude_m: Altitude | None = Field(
        None, description="hexacopter only: height above the terrain under the waypoint"
    )
    scan: bool = Field(False, description="360 deg scan on arrival (pan head on rovers, yaw on ardea)")


class RouteConfig(StrictModel):
    speed_mps: PositiveFloat = Field(0.3, description=f"travel speed along each leg (at most per preset: {_per_preset('max_speed_mps')})")
    tolerance_m: PositiveFloat = Field(0.35, description="a waypoint counts as reached within this horizontal distance")
    waypoints: list[WaypointConfig] = Field(
        [], description="the waypoints in order, short forms [x, y] and [x, y, altitude_m]; none: the robot stays at its start"
    )
    scan_duration_s: PositiveFloat = Field(20.0, description="length of the 360 deg turn at a waypoint with scan: true")
    scan_tilt_deg: float | None = Field(
        None, ge=-45, le=90, description="rover head tilt during scans (positive looks down; default: the preset's 25 deg)"
    )
    head_sweep_deg: float | None = Field(
        None, ge=0, le=90, description="rover head pan amplitude while driving, +- around straight ahead (default: the preset's; 0: none)"
    )
    head_sweep_period_s: PositiveFloat | None = Field(None, description="period of the rover head's sweep while driving (default: the preset's)")
    cruise_altitude_m: Altitude = Field(3.0, description="hexacopter default height above terrain")
    land: bool = Field(False, description="hexacopter lands after the last waypoint")
    stuck_timeout_s: PositiveFloat = Field(15.0, description="no progress for this long counts as stuck")
    start_delay_s: NonNegFloat = Field(
        1.0, description="stand still this long before moving (the filter initialises roll and pitch at rest)"
    )

    @field_validator("waypoints", mode="before")
    @classmethod
    def _short_form(cls, value: Any) -> Any:
        """Accept ``[x, y]`` and ``[x, y, altitude]`` as short forms of a waypoint."""
        if not isinstance(value, list):
            return value
        out = []
        for item in value:
            if isinstance(item, (list, tuple)) and len(item) in (2, 3):
                wp: dict[str, Any] = {"xy": list(item[:2])}
                if len(item) == 3:
                    wp["altitude_m"] = item[2]
                out.append(wp)
            else:
                out.append(item)
        return out


class StartConfig(StrictModel):
    xy: XY = Field(
        (0.0, 0.0),
        description="start position (m, origin at the terrain centre); two robots start at least the sum of their presets' body radii apart",
    )
    yaw_deg: float = Field(0.0, description="start heading, counter-clockwise from +x")


class ComputerConfig(StrictModel):
    """The robot's on-board computer (thesis 7.1: rovers quad-core i7, ARDEA dual-core,
    both with an FPGA for dense stereo)."""

    cores: int | None = Field(None, ge=1, le=64, description=f"default per preset: {_per_preset('default_cores')}")
    fpga: bool = Field(True, description="stereo matching runs on its own FPGA device")


class NavigationConfig(StrictModel):
    """What the robot's guidance steers by (thesis 9.3: the rovers navigated on their
    on-board estimates and obstacle maps)."""

    pose_source: Literal["truth", "estimate"] = Field(
        "truth",
        description=(
            "truth: the controller reads the simulator's pose and drives straight at each waypoint (scripted scenarios); "
            f"estimate: it steers by the robot's own online SLAM pose (eq. 4.6) and plans around the obstacles on its rolling "
            f"obstacle map (needs slam.enabled and slam.mapping.enabled; presets: {_per_preset('navigates_on_estimate')})"
        ),
    )
    replan_period_s: PositiveFloat = Field(1.0, le=30, description="estimate: the path is planned again this often on the map as it is then")
    lookahead_m: PositiveFloat = Field(0.8, le=5, description="estimate: the controller steers at the path's point this far ahead")


class ExplorationConfig(StrictModel):
    """Frontier-based multi-robot exploration of a target region (thesis 9.3;
    slam/navigation/exploration.py): each exploring robot drives to goals it chooses on its
    own map, scans there, and tells the team its goals."""

    region: list[XY] = Field(..., min_length=3, description="the target region: a polygon of [x, y] vertices (m, origin at the terrain centre)")
    robots: list[str] | None = Field(
        None, min_length=1, description=f"the robots that explore (default: every robot whose preset can: {_per_preset('explores')})"
    )
    cell_m: PositiveFloat = slam_field(SlamParam(ExplorationParams, "cell_m"), description="cells of the explored-area grid")
    sensor_range_m: PositiveFloat = slam_field(
        SlamParam(ExplorationParams, "sensor_range_m"), description="a goal's information gain counts the unexplored cells within this range of it"
    )
    goal_separation_m: NonNegFloat = slam_field(
        SlamParam(ExplorationParams, "goal_separation_m"),
        description="keep goals this far from the peers' current goals (thesis 9.3: 7 m, about twice the sensor range)",
    )
    distance_weight: NonNegFloat = slam_field(
        SlamParam(ExplorationParams, "distance_weight"), description="a goal's utility is gain x exp(-distance_weight x distance) (1/m)"
    )
    coverage_target: float = slam_field(
        SlamParam(ExplorationParams, "coverage_target"), gt=0, le=1, description="a robot stops exploring once it believes this fraction is explored"
    )
    min_gain_cells: int = slam_field(
        SlamParam(ExplorationParams, "min_gain_cells"), ge=1, description="frontiers that would explore fewer cells are no goals"
    )
    min_goal_distance_m: NonNegFloat = slam_field(
        SlamParam(ExplorationParams, "min_goal_distance_m"), description="no goal nearer than this to the robot"
    )
    loop_closing_weight: NonNegFloat = slam_field(
        SlamParam(ExplorationParams, "loop_closing_weight"),
        description="active loop closing: a revisit's utility is this (cells per nat) x its expected information"
        " x exp(-distance_weight x distance); 0: off (the thesis)",
    )
    loop_closing_match_sigma_m: PositiveFloat = slam_field(
        SlamParam(ExplorationParams, "loop_closing_match_sigma_m"),
        description="active loop closing: the position sigma a match would leave at a revisited place",
    )
    observe_peers: bool = slam_field(
        SlamParam(ExplorationParams, "observe_peers"),
        description="active mutual observation: point the head at a peer believed within observe_range_m",
    )
    observe_range_m: PositiveFloat = slam_field(
        SlamParam(ExplorationParams, "observe_range_m"), description="active mutual observation: look for peers this near"
    )
    observe_interval_s: NonNegFloat = slam_field(
        SlamParam(ExplorationParams, "observe_interval_s"), description="active mutual observation: look for a peer not detected for this long"
    )
    initial_scan: bool = Field(True, description="scan where it stands before choosing its first goal")
    scan_at_goal: bool = Field(True, description="scan 360 deg at every goal (route.scan_duration_s)")

    def explorers(self, robots: list[RobotConfig]) -> list[str]:
        """Names of the exploring robots."""
        return self.robots if self.robots is not None else [r.name for r in robots if PRESETS[r.preset].explores]


class RobotConfig(StrictModel):
    name: str = Field(..., pattern=NAME_PATTERN, description="unique robot name, also its network node ('lander' is taken)")
    preset: Literal["lru", "lru_wide", "ardea"] = Field(
        ..., description="robot type (thesis 7.1): lru (rover, narrow stereo), lru_wide (rover, wide-angle stereo), ardea (hexacopter)"
    )
    start: StartConfig = Field(StartConfig(), description="start pose; the robot starts resting on the ground")
    tag_ids: list[Annotated[int, Field(ge=0, le=586)]] | None = Field(
        None, description="AprilTag 36h11 ids of the robot's markers (default: assigned from 1 up)"
    )
    route: RouteConfig = Field(RouteConfig(), description="waypoints and how the robot drives or flies them")
    camera: CameraConfig = Field(CameraConfig(), description="the rendered stereo cameras (every rig of the robot)")
    imu: ImuConfig = Field(ImuConfig(), description="the inertial measurement unit")
    wheel_odometry: WheelOdometryConfig = Field(WheelOdometryConfig(), description="wheel encoder odometry (rovers only)")
    computer: ComputerConfig = Field(ComputerConfig(), description="the on-board computer that runs the robot's jobs")
    navigation: NavigationConfig = Field(NavigationConfig(), description="what the robot's guidance steers by")

    @property
    def marker_count(self) -> int:
        return PRESETS[self.preset].marker_count

    @model_validator(mode="after")
    def _check_preset_fields(self) -> RobotConfig:
        PRESETS[self.preset].check_config(self)
        return self


# --------------------------------------------------------------------------- run


class PhysicsConfig(StrictModel):
    timestep_s: float = Field(
        0.001,
        ge=1e-4,
        le=0.01,
        description="MuJoCo physics step",
        json_schema_extra={"why": "MuJoCo steps the robots stably in 0.1-10 ms; finer only costs"},
    )
    control_rate_hz: float = Field(
        200.0,
        ge=10,
        le=1000,
        description="controllers and IMU sampling tick",
        json_schema_extra={"why": "the controllers are tuned for 200 Hz; a tick holds at most 1000 physics steps"},
    )


class StageCosts(StrictModel):
    """Modelled compute time per job (s). Defaults from thesis 7.1 and 8.4."""

    stereo_s: NonNegFloat = Field(1 / 14.6, description="FPGA SGM at up to 14.6 Hz (thesis 7.1)")
    vo_s: NonNegFloat = Field(
        0.25 - 1 / 14.6, description="keyframe VO on a core; with stereo about 250 ms from capture to delta pose (thesis 4.1.1)"
    )
    strapdown_s: NonNegFloat = Field(1e-5, description="strapdown step per IMU sample (thesis 8.4: < 0.01 ms)")
    filter_update_s: NonNegFloat = Field(2e-4, description="Kalman update: VO delta, wheel odometry (thesis 8.4: 0.2 ms mean)")
    mapping_s: NonNegFloat = Field(
        0.01, description="obstacle classification and submap integration of one depth image (thesis 8.4: 0.01 s mean integration)"
    )
    detection_s: NonNegFloat = Field(0.01, description="AprilTag detection and PnP in one image (chosen; the thesis gives no figure)")
    pairing_s: NonNegFloat = Field(0.39, description="keypoints of new submaps, the pair queue (thesis 8.1: 0.39 s keypoints and features per map)")
    matching_s: NonNegFloat = Field(
        3.09, description="one submap pair: feature matching 3.07 s and Hough voting 0.02 s (thesis 8.4), the ICP apart (icp_s)"
    )
    icp_s: NonNegFloat = Field(2.38, description="ICP refinement of a pair's best hypothesis, only for pairs that reach it (thesis 8.4)")
    messages_s: NonNegFloat = Field(1e-4, description="decoding a peer message and adding its factors")
    graph_s: NonNegFloat = Field(0.0017, description="one iSAM2 update (thesis 8.4: 1.7 ms mean)")
    exploration_s: NonNegFloat = Field(
        0.5, description="choosing an exploration goal on the robot's map (chosen; thesis 9.3 gives no figure)"
    )


class ComputeConfig(StrictModel):
    model: Literal["modeled", "measured"] = Field(
        "modeled", description="modeled: a job takes its stage's cost from stages; measured: its wall time on this machine x measured_scale"
    )
    measured_scale: PositiveFloat = Field(1.0, description="measured mode: wall time x this factor")
    stages: StageCosts = Field(StageCosts(), description="modelled compute time per job stage (model: modeled)")
    max_queue: int = Field(2, ge=1, le=1000, description="real-time jobs waiting beyond this are dropped")


class OutputConfig(StrictModel):
    recording: bool = Field(True, description="write the rerun recording recording.rrd")
    recording_image_every: int = Field(5, ge=1, description="log every n-th camera frame to the recording")
    recording_image_scale: float = Field(
        0.5, gt=0, le=1, description="camera images go into the recording at this fraction of their width and height"
    )
    topdown_png: bool = Field(True, description="write the plots topdown.png, filter_error.png, slam.png and map_topdown.png")
    dataset: Literal["euroc"] | None = Field(
        None,
        description="euroc: write every robot's camera images (every frame, as the SLAM stack gets them), IMU, wheel odometry and ground "
        "truth in the EuRoC MAV layout to dataset/<robot>/mav0/, for OpenVINS, ORB-SLAM3, VINS-Fusion or Kimera; null: no dataset",
    )


class MappingConfig(StrictModel):
    """Obstacle classification and submaps (thesis ch. 5); a new submap switches the filter's frame."""

    enabled: bool = Field(True, description="false: no map; the filter switches frames after slam.frame_switch_distance_m")
    submap_position_std_m: PositiveFloat = slam_field(
        SlamParam(SubmapParams, "max_position_std_m"),
        description="new submap when the filter's position std exceeds this (thesis 5.1.3: 0.1-0.2 m)",
    )
    submap_distance_m: PositiveFloat = slam_field(
        SlamParam(SubmapParams, "max_distance_m"), description="new submap after this distance in the current one (thesis: 3.5 or 7 m)"
    )
    point_resolution_m: float = slam_field(
        SlamParam(SubmapParams, "point_resolution_m"),
        ge=0.005,
        le=1.0,
        description="submap point cloud voxel filter (thesis 5.1.2)",
        json_schema_extra={"why": "stereo depth is no finer than about 1 cm at 1 m; finer cells only multiply the points"},
    )
    voxel_resolution_m: float = slam_field(
        SlamParam(SubmapParams, "voxel_resolution_m"),
        ge=0.01,
        le=2.0,
        description="submap occupancy voxels (thesis 5.1.2)",
        json_schema_extra={"why": "voxel keys pack 21 bits per axis (slam/voxels.py): 1 cm cells span 20 km"},
    )
    max_depth_error_m: PositiveFloat = slam_field(
        SlamParam(SubmapParams, "max_depth_error_m"),
        SlamParam(ObstacleParams, "max_error_m"),
        description="points whose depth error (eq. 5.2c) exceeds this are dropped",
    )
    pixel_error_px: PositiveFloat = slam_field(
        SlamParam(ObstacleParams, "pixel_error"),
        description="Δp of eq. 5.2 and 5.4 in the obstacle classification (thesis 0.5 px): with max_depth_error_m its far cut; the step thresholds",
    )
    submap_pixel_error_px: PositiveFloat = slam_field(
        SlamParam(SubmapParams, "pixel_error"),
        description="Δp of eq. 5.2c for the submaps' far cut (with max_depth_error_m): the disparity error stereo really has "
        "(docs/matching.md, 'Mapping range'), so submaps reach as far as their points are accurate",
    )
    step_height_m: PositiveFloat = slam_field(
        SlamParam(ObstacleParams, "step_height_m"), description="h_max: highest step the robot drives over (thesis 5.1.1)"
    )
    max_slope_deg: float = slam_field(
        SlamParam(ObstacleParams, "max_slope_rad", degrees=True),
        gt=0,
        lt=90,
        description="steepest traversable slope, for negative edges (eq. 5.1)",
    )
    window_cells: int = slam_field(
        SlamParam(ObstacleParams, "window_cells"),
        ge=3,
        le=6,
        description="h_diff window of the 2.5D height map, 0.05 m cells (thesis 5.1.1)",
    )


class GraphConfig(StrictModel):
    """The multi-robot pose graph and the exchange between robots (thesis 4.2, 3.3)."""

    enabled: bool = Field(True, description="false: filter only, no graph optimisation, no messages, no detections")
    topology: Literal["local_reference", "sequential"] = slam_field(
        SlamParam(GraphParams, "topology"),
        description="thesis 4.2.2: filter estimates on submap origins, or sequential odometry (eq. 4.8-4.9)",
    )
    robust: Literal["cauchy", "gnc", "none"] = slam_field(
        SlamParam(GraphParams, "robust"),
        description="detections, matches and landmark observations: Cauchy kernel (thesis 4.2.3, eq. 4.10), "
        "Graduated Non-Convexity outlier rejection (Yang et al. 2020) or plain Gaussian",
    )
    cauchy_c: PositiveFloat = slam_field(
        SlamParam(GraphParams, "cauchy_c"),
        description="robust: cauchy: the kernel's constant (eq. 4.10), Mahalanobis units",
    )
    gnc_inlier_probability: float = slam_field(
        SlamParam(GraphParams, "gnc_inlier_probability"),
        gt=0,
        lt=1,
        description="robust: gnc: an inlier's squared Mahalanobis distance is below this chi-square quantile (6 dof)",
    )
    pose_period_s: PositiveFloat = slam_field(
        SlamParam(AgentParams, "pose_period_s"), description="each robot broadcasts its pose estimate this often"
    )
    covariance_period_s: PositiveFloat = slam_field(
        SlamParam(AgentParams, "covariance_period_s"), description="marginal covariances of the latest submap origins this often"
    )
    pose_buffer_s: PositiveFloat = slam_field(
        SlamParam(AgentParams, "buffer_horizon_s"), description="how far back a robot can answer a detection of itself"
    )


class DetectionConfig(StrictModel):
    """AprilTag robot detections and landmark observations (thesis 6.2.1)."""

    enabled: bool = Field(True, description="detect the AprilTags of robots and the lander (needs slam.graph)")
    uncertainty: Literal["constant", "quadratic", "lut", "online", "lut_online"] = slam_field(
        SlamParam(AgentParams, "uncertainty"),
        description="eq. 8.1, eq. 8.2, or thesis 6.2.3: lookup table (assets/marker_lut, `marsyard marker-lut`), corner perturbation, both",
    )
    min_interval_s: NonNegFloat = slam_field(
        SlamParam(AgentParams, "detection_interval_s"), description="at most one detection of each target per interval"
    )
    max_distance_m: PositiveFloat = slam_field(
        SlamParam(AgentParams, "max_detection_distance_m"), description="markers farther than this are not used"
    )
    max_tilt_deg: float = slam_field(
        SlamParam(AgentParams, "max_target_tilt_rad", degrees=True),
        gt=0,
        le=90,
        description="of PnP's two solutions the one with the target closest to upright, if tilted at most this",
    )
    max_ambiguity: float = slam_field(
        SlamParam(AgentParams, "max_ambiguity"),
        gt=0,
        le=1.0,
        description="PnP's best over second-best reprojection error at most this (near 1 the planar pose is ambiguous)",
    )


class MatchingConfig(StrictModel):
    """Submap matching (thesis 6.1): intra- and inter-robot loop closures ``c``."""

    enabled: bool = Field(True, description="match submaps in the background (needs slam.mapping and slam.graph)")
    mode: Literal["4d", "6d", "4d+6d"] = slam_field(
        SlamParam(MatcherParams, "mode"),
        description="thesis 6.1.2: gravity-aligned 4D alignment and ICP, 6D (8.1.2's baseline), or 4D alignment refined by a 6D ICP (8.1.2)",
    )
    keypoints: Literal["obstacles", "geometry", "both"] = slam_field(
        SlamParam(MatcherParams, "keypoints"),
        description="keypoints from obstacle points (thesis 6.1.1), salient local geometry (surface variation; 9.3), or both",
    )
    voting: Literal["hough3d", "yaw_sweep"] = slam_field(
        SlamParam(MatcherParams, "voting"),
        description="clusters of correspondences: Hough3D with local reference frames (thesis 6.1.2), or every yaw of a 2 deg "
        "grid voting for translations, no reference frames (ours; the submaps are gravity-aligned)",
    )
    icp_points: Literal["all", "classified"] = slam_field(
        SlamParam(MatcherParams, "icp_points"),
        description="the ICP refinement aligns the whole clouds, or only their points within the obstacle classification's "
        "range (stereo depth error and a calibration's depth bias grow with z^2, eq. 5.2c)",
    )
    sweep_within_prior: bool = slam_field(
        SlamParam(MatcherParams, "sweep_within_prior"),
        description="ours: the yaw sweep votes only for translations the 2-sigma plausibility check can accept, as it sweeps "
        "only such yaws",
    )
    icp_from_prior: bool = slam_field(
        SlamParam(MatcherParams, "icp_from_prior"),
        description="ours: a second ICP started at the graph's prediction of the pair; the match keeps whichever ends at the lower truncated cost",
    )
    min_overlap_m2: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "min_overlap_m2"),
        description="eq. 6.2: xy overlap of the obstacle bounding boxes, widened by 2 relative sigmas",
    )
    stereo_error_depth_m: PositiveFloat = Field(
        2.0, description="p_z of eq. 6.3: pairs more certain than the stereo error at this depth are skipped (thesis: 4 m for its LRU)"
    )
    sigma_scale: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "sigma_scale"),
        description="the graph's relative sigmas are multiplied by this in eq. 6.1-6.4 and the 2-sigma checks (>1: an overconfident filter)",
    )
    sigma_bound: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "sigma_bound"),
        description="hypotheses and results must lie within this many relative sigmas of the graph",
    )
    descriptor: Literal["fpfh", "spin"] = slam_field(
        SlamParam(MatcherParams, "descriptor"),
        description="keypoint descriptors: FPFH (a stand-in for the thesis's CSHOT, 6.1.2), or spin images about the gravity "
        "axis (ours; yaw-invariant, no normals or reference frames)",
    )
    descriptor_radius_m: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "descriptor_radius_m"), description="FPFH radius (and of the known-space check around keypoints)"
    )
    spin_radius_m: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "spin_radius_m"), description="spin images: the neighbourhood's horizontal radius about the vertical axis"
    )
    spin_height_m: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "spin_height_m"), description="spin images: heights within +-this of the keypoint (beyond: the edge bins)"
    )
    spin_bins: int = slam_field(SlamParam(MatcherParams, "spin_bins"), ge=2, description="spin images: bins of distance and of height each")
    descriptor_resolution_m: NonNegFloat = slam_field(
        SlamParam(MatcherParams, "descriptor_resolution_m"),
        description=(
            "> 0: FPFH on the cloud voxel-filtered at this size (voxel-averaged normals; "
            "at 0.1 m its 100 neighbours reach the 0.4 m radius); 0: full cloud"
        ),
    )
    max_descriptor_distance: float = slam_field(
        SlamParam(MatcherParams, "max_descriptor_distance"),
        gt=0,
        le=1,
        description="L2 between unit descriptors (FPFH or spin images), scaled to [0, 1]",
    )
    max_icp_rmse_m: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "max_icp_rmse_m"), description="a refined match with a larger point-to-point RMSE is rejected"
    )
    icp_outlier_m: PositiveFloat = slam_field(
        SlamParam(MatcherParams, "icp_outlier_m"),
        description="the ICP's truncated least squares: a point-to-plane residual beyond this, or a point without a partner, costs this much",
    )
    icp_intensity_scale_m: NonNegFloat = slam_field(
        SlamParam(MatcherParams, "icp_intensity_scale_m"),
        description="ours: > 0 adds the points' intensities to the ICP (a coloured ICP, Park et al. 2017), an intensity residual "
        "of 1 (the submap's median intensity) weighing as a point-to-plane residual of this many metres; 0: geometry alone (the thesis)",
    )


class HealthConfig(StrictModel):
    """When a robot's estimator calls itself degraded or lost (slam/health.py)."""

    vo_timeout_s: PositiveFloat = slam_field(
        SlamParam(HealthParams, "vo_timeout_s"), description="degraded after this long without an applied VO delta while not resting"
    )
    lost_after_s: PositiveFloat = slam_field(SlamParam(HealthParams, "lost_after_s"), description="lost after this long degraded")
    max_position_std_m: PositiveFloat | None = slam_field(
        SlamParam(HealthParams, "max_position_std_m"), description="lost when the position std in the local frame exceeds this (null: no bound)"
    )
    max_velocity_std_mps: PositiveFloat | None = slam_field(
        SlamParam(HealthParams, "max_velocity_std_mps"), description="lost when the velocity std exceeds this (null: no bound)"
    )


class SlamConfig(StrictModel):
    """The on-board estimation stack of every robot (thesis ch. 4)."""

    enabled: bool = Field(True, description="false: no on-board estimation at all")
    vo_rig: str | None = Field(None, description=f"stereo rig used for VO (default per preset: {_per_preset('default_vo_rig')})")
    wheel_odometry: bool = Field(True, description="robots with wheel encoders (the rovers) fuse wheel odometry as body-velocity updates")
    wheel_speed_std_mps: PositiveFloat = slam_field(
        SlamParam(LocalEstimator.on_wheel_odometry, "speed_std"),
        default=0.03,
        description="velocity noise the filter assumes for wheel odometry: sensor noise plus unmodelled slip",
    )
    wheel_yaw_rate_std_rps: PositiveFloat = slam_field(
        SlamParam(LocalEstimator.on_wheel_odometry, "yaw_rate_std"),
        default=0.03,
        description="yaw-rate noise the filter assumes for wheel odometry",
    )
    wheel_vz_std_mps: PositiveFloat = slam_field(
        SlamParam(LocalEstimator.on_wheel_odometry, "vz_std"), description="std of the rover's v_z = 0 pseudo-measurement"
    )
    wheel_slip_std: NonNegFloat = slam_field(
        SlamParam(LocalEstimator.on_wheel_odometry, "slip_std"),
        description="relative wheel-speed error from slip and rolling radius the filter assumes (0: none)",
    )
    wheel_slip_correlation_s: PositiveFloat = slam_field(
        SlamParam(LocalEstimator.on_wheel_odometry, "slip_correlation_s"), description="correlation time of that error"
    )
    gyro_scale_std: NonNegFloat = slam_field(
        SlamParam(FilterParams, "gyro_scale_std"),
        description="relative gyro scale and misalignment error the filter allows for in turns (0: none)",
    )
    gyro_scale_correlation_s: PositiveFloat = slam_field(
        SlamParam(FilterParams, "gyro_scale_correlation_s"), description="correlation time of that error"
    )
    accel_misalignment_std_deg: NonNegFloat = slam_field(
        SlamParam(FilterParams, "accel_misalignment_std", degrees=True),
        description="std of the accelerometer z axis's lean towards x and y, held by the filter as consider parameters (0: none)",
    )
    vo_disparity_bias_px: NonNegFloat = slam_field(
        SlamParam(FilterParams, "disparity_bias_std"),
        SlamParam(VoParams, "disparity_offset_prior_px"),
        description="std of a disparity offset common to all VO points (rectification error), held by the filter as a consider parameter"
        " and the prior of each coefficient of its online estimate",
    )
    vo_disparity_offset_estimation: bool = slam_field(
        SlamParam(VoParams, "estimate_disparity_offset"),
        description="estimate the VO rig's disparity offset while moving and take it off the VO's and the mapping's depths "
        "(slam/stereo_offset.py; false: the calibration as given, thesis 5.1.1)",
    )
    vo_disparity_offset_model: Literal["yaw", "rotation"] = slam_field(
        SlamParam(VoParams, "disparity_offset_model"),
        description="what the online estimate models: the right camera's yaw alone (its offset, larger towards the image's "
        "sides) or its whole rotation error (yaw, roll and pitch, each offsetting the disparities in its own pattern; roll "
        "and pitch read off the stereo matches' rows; slam/stereo_offset.py, docs/realism.md)",
    )
    camera_rotation_std_deg: NonNegFloat = slam_field(
        SlamParam(FilterParams, "extrinsic_rotation_std", degrees=True),
        description="std per axis of the VO camera-IMU calibration's rotation, held by the filter as consider parameters",
    )
    camera_translation_std_m: NonNegFloat = slam_field(
        SlamParam(FilterParams, "extrinsic_translation_std"),
        description="std per axis of the VO camera-IMU calibration's translation, held by the filter as consider parameters",
    )
    vo_focal_scale_std: NonNegFloat = slam_field(
        SlamParam(FilterParams, "focal_scale_std"),
        description="relative std of the VO rig's focal length (both cameras alike), held by the filter as a consider parameter:"
        " it scales the VO's rotations (0: none; docs/realism.md, \"The VO's turns\")",
    )
    vo_keyframe_map_error: bool = slam_field(
        SlamParam(FilterParams, "keyframe_map_error"),
        description="the VO deltas' error from their keyframe's 3D points enters once per keyframe, not with every delta (false: thesis 4.1.1)",
    )
    frame_switch_distance_m: PositiveFloat = Field(
        5.0, description="without mapping only: frame switch after this distance driven in the current frame"
    )
    mapping: MappingConfig = Field(MappingConfig(), description="obstacle classification and submaps (thesis ch. 5)")
    graph: GraphConfig = Field(GraphConfig(), description="the multi-robot pose graph and the message exchange (thesis 4.2, 3.3)")
    detections: DetectionConfig = Field(DetectionConfig(), description="AprilTag robot detections and landmark observations (thesis 6.2)")
    matching: MatchingConfig = Field(MatchingConfig(), description="submap matching for loop closures (thesis 6.1)")
    initial_rest_s: PositiveFloat = Field(
        0.5,
        description="roll and pitch initialised from the mean accelerometer reading over this long before the route starts",
    )
    zero_velocity: bool = slam_field(
        SlamParam(RestParams, "zero_velocity"),
        description="zero-velocity updates while the robot rests (slam/rest.py: IMU rest test, vetoed by motion commands, wheels and VO)",
    )
    health: HealthConfig = Field(HealthConfig(), description="when a robot's estimator calls itself degraded or lost")


# --------------------------------------------------------------------------- realism


class CameraRealism(StrictModel):
    """Image formation of the cameras (sim/world/imaging.py; thesis 6.2.1: noise,
    discretisation, over- and underexposure)."""

    noise: bool | None = Field(None, description="photon shot noise and read noise of the thesis's Guppy PRO F-125B")
    auto_exposure: bool | None = Field(None, description="exposure and gain follow the scene (saturation where it is bright)")
    vignetting: float | None = Field(None, ge=0, lt=1, description="relative illumination lost at the image corners")
    motion_blur: bool | None = Field(None, description="blur from the camera's rotation during the exposure")
    right_gain_error_std: NonNegFloat | None = Field(None, description="std of the right camera's relative response error (drawn per robot)")


class CalibrationRealism(StrictModel):
    """What the robot's calibration got wrong (sim/world/calibration_errors.py): the true
    cameras differ from the ones the SLAM stack believes in, by errors drawn per robot."""

    stereo_rotation_deg: NonNegFloat | None = Field(None, description="std per axis of the right camera's rotation against the rectified pair")
    baseline_error: NonNegFloat | None = Field(None, description="std of the relative stereo baseline error")
    focal_error: NonNegFloat | None = Field(None, description="std of the relative focal length error (both cameras)")
    camera_imu_rotation_deg: NonNegFloat | None = Field(None, description="std per axis of the camera-IMU rotation error")
    camera_imu_translation_m: NonNegFloat | None = Field(None, description="std per axis of the camera-IMU translation error")
    pan_tilt_offset_deg: NonNegFloat | None = Field(None, description="std of the pan and tilt encoders' zero offsets (robots with a pan-tilt head)")
    lens_distortion_mrad: NonNegFloat | None = Field(
        None, description="expected RMS over the image of each camera's lens distortion left after rectification (mrad of viewing direction)"
    )
    camera_imu_time_offset_ms: NonNegFloat | None = Field(
        None, le=50, description="std of the time the cameras take a pair after the stamp the stack gives it (one offset per robot)"
    )


class ImuRealism(StrictModel):
    """IMU errors beyond white noise and bias random walks (sim/world/sensors.py)."""

    scale_factor: NonNegFloat | None = Field(None, description="std of each axis's relative scale factor error")
    misalignment_deg: NonNegFloat | None = Field(None, description="std of each sensitive axis's misalignment")
    g_sensitivity_dps_per_g: NonNegFloat | None = Field(None, description="std of each gyro axis's sensitivity to specific force")


class WheelRealism(StrictModel):
    """Wheel odometry errors the physics does not produce (sim/world/sensors.py): loose regolith and radius."""

    radius_error: NonNegFloat | None = Field(None, description="std of the relative error of the radius the odometry assumes")
    slip: NonNegFloat | None = Field(None, description="longitudinal slip ratio on level ground (wheels turn this much more than the ground passes)")
    slip_per_10deg: NonNegFloat | None = Field(None, description="slip ratio added per 10 deg of uphill gradient (removed downhill)")
    slip_std: NonNegFloat | None = Field(None, description="std of the slip ratio's variation with the soil (5 s correlation time)")


class LightRealism(StrictModel):
    """Lighting (sim/world/terrain.py): the sun, its shadows and a camera-fixed fill light."""

    shadows: bool | None = Field(None, description="the sun casts shadows (costly on CPU rendering: docs/realism.md)")
    sun_elevation_deg: float | None = Field(None, gt=0, le=90, description="default: the terrain preset's")
    sun_azimuth_deg: float | None = Field(None, description="direction of the sun, counter-clockwise from +x (default: the terrain preset's)")
    headlight: bool | None = Field(None, description="a fill light that moves with the camera (no real rover has one in daylight)")
    albedo_contrast_scale: PositiveFloat | None = Field(
        None, le=2.0, description="the regolith albedo texture's contrast (terrain.texture.contrast) times this"
    )


#: The values of each ``realism.profile``, and the one place they are set. ``ideal`` is
#: the world before imperfections were modelled (for tests that need exact numbers);
#: ``realistic`` was tuned towards the thesis's filter drift on Etna-like runs (8.3: 0.7-2 %
#: of distance; with the filter's later improvements it drifts less, docs/realism.md); ``harsh`` doubles the
#: calibration, IMU and wheel errors. Sources of the ``realistic`` values:
#: - camera: Allied Vision Guppy PRO F-125B (thesis 7.1), with the sources of its noise,
#:   exposure, vignetting and response spread in sim/world/imaging.py;
#: - calibration: stereo rotation 0.04 deg and focal 0.2 % are a calibration's residual
#:   plus what transport and temperature change afterwards (DLR CalDe/CalLab, Strobl and
#:   Hirzinger 2008, reach 0.1-0.2 px reprojection error, 0.005-0.01 deg at the Guppy's
#:   1333 px focal length; field rigs drift further: chosen at 4-8x of that, tuned
#:   against the thesis's drift, docs/realism.md); baseline 0.1 % (0.09 mm of 9 cm);
#:   camera-IMU 0.2 deg and 5 mm (hand-eye calibration, thesis 4.1 uses a calibrated
#:   head); pan-tilt encoder offsets 0.1 deg (chosen); lens distortion left after
#:   rectification 0.2 mrad RMS (thesis 5.1.1: the LRU's calibrations had an RMSE of up to
#:   0.46 px, 0.35 mrad at 1333 px, "larger in the outer parts of the image"; that RMSE
#:   also holds the corner detector's noise, so the model's residual is taken below it:
#:   0.27 px at the Guppy's resolution, 0.07 px at 320x240); camera-IMU time offset 2 ms
#:   (chosen: the thesis states no temporal calibration between its hardware-triggered
#:   cameras and the IMU on its serial link; host time stamps leave transfer latencies and
#:   the exposure's middle against the trigger, milliseconds, which visual-inertial
#:   calibration estimates, Furgale et al. 2013, Li and Mourikis 2014; quoted from memory);
#: - IMU: Xsens MTi-10 data sheet (MT0605P, quoted from memory): gyro scale non-linearity
#:   and misalignment 0.05 deg-class after factory calibration; g-sensitivity 0.001 deg/s/g
#:   class for MEMS gyros (ADIS16407: 0.05 deg/s/g without compensation); scale 0.1 %;
#: - wheels: slip on loose soil 2 % on level ground and about 5-10 % per 10 deg uphill
#:   (Lindemann and Voorhees 2005, MER slip tests; quoted from memory), radius 1 %
#:   (tyre compliance and sinkage);
#: - light: shadows off by default (their cost on 2 cores, docs/realism.md), no headlight;
#:   the albedo texture at half the ideal world's contrast (0.35 was chosen for SGBM to
#:   match easily), so that more of the image comes from shading: tuned
#:   against the thesis's drift (docs/realism.md).
REALISM_PROFILES: dict[str, dict[str, dict[str, Any]]] = {
    "ideal": {
        "camera": {"noise": False, "auto_exposure": False, "vignetting": 0.0, "motion_blur": False, "right_gain_error_std": 0.0},
        "calibration": {
            "stereo_rotation_deg": 0.0,
            "baseline_error": 0.0,
            "focal_error": 0.0,
            "camera_imu_rotation_deg": 0.0,
            "camera_imu_translation_m": 0.0,
            "pan_tilt_offset_deg": 0.0,
            "lens_distortion_mrad": 0.0,
            "camera_imu_time_offset_ms": 0.0,
        },
        "imu": {"scale_factor": 0.0, "misalignment_deg": 0.0, "g_sensitivity_dps_per_g": 0.0},
        "wheels": {"radius_error": 0.0, "slip": 0.0, "slip_per_10deg": 0.0, "slip_std": 0.0},
        "light": {"shadows": False, "sun_elevation_deg": None, "sun_azimuth_deg": None, "headlight": True, "albedo_contrast_scale": 1.0},
    },
    "realistic": {
        "camera": {"noise": True, "auto_exposure": True, "vignetting": 0.3, "motion_blur": True, "right_gain_error_std": 0.02},
        "calibration": {
            "stereo_rotation_deg": 0.04,
            "baseline_error": 0.001,
            "focal_error": 0.002,
            "camera_imu_rotation_deg": 0.2,
            "camera_imu_translation_m": 0.005,
            "pan_tilt_offset_deg": 0.1,
            "lens_distortion_mrad": 0.2,
            "camera_imu_time_offset_ms": 2.0,
        },
        "imu": {"scale_factor": 0.001, "misalignment_deg": 0.05, "g_sensitivity_dps_per_g": 0.001},
        "wheels": {"radius_error": 0.01, "slip": 0.02, "slip_per_10deg": 0.07, "slip_std": 0.02},
        "light": {"shadows": False, "sun_elevation_deg": None, "sun_azimuth_deg": None, "headlight": False, "albedo_contrast_scale": 0.5},
    },
}
REALISM_PROFILES["harsh"] = {
    **REALISM_PROFILES["realistic"],
    "calibration": {k: 2 * v for k, v in REALISM_PROFILES["realistic"]["calibration"].items()},
    "imu": {k: 2 * v for k, v in REALISM_PROFILES["realistic"]["imu"].items()},
    "wheels": {k: 2 * v for k, v in REALISM_PROFILES["realistic"]["wheels"].items()},
    "light": {**REALISM_PROFILES["realistic"]["light"], "shadows": True},
}


class RealismConfig(StrictModel):
    """How far the simulated world departs from the ideal one. ``profile`` sets every
    value (:data:`REALISM_PROFILES`); a key set in a section overrides its profile's."""

    profile: Literal["ideal", "realistic", "harsh"] = Field(
        "realistic",
        description="ideal (no imperfections), realistic (tuned to the thesis's drift, 8.3) or harsh (doubled calibration, IMU and "
        "wheel errors, shadows); it sets every key below that is left out or null",
    )
    camera: CameraRealism = Field(CameraRealism(), description="image formation of the cameras; a key left out or null takes the profile's value")
    calibration: CalibrationRealism = Field(
        CalibrationRealism(), description="calibration errors, drawn per robot; a key left out or null takes the profile's value"
    )
    imu: ImuRealism = Field(
        ImuRealism(), description="IMU scale, misalignment and g-sensitivity errors; a key left out or null takes the profile's value"
    )
    wheels: WheelRealism = Field(WheelRealism(), description="wheel slip and radius errors; a key left out or null takes the profile's value")
    light: LightRealism = Field(LightRealism(), description="sun, shadows and fill light; a key left out or null takes the profile's value")

    @model_validator(mode="after")
    def _fill_from_profile(self) -> RealismConfig:
        for section, values in REALISM_PROFILES[self.profile].items():
            model = getattr(self, section)
            missing = {k: v for k, v in values.items() if getattr(model, k) is None}
            if missing:
                object.__setattr__(self, section, model.model_copy(update=missing))
        return self


# --------------------------------------------------------------------------- faults


class FaultEntry(StrictModel):
    """What every injected failure has: the robots it hits and when (sim/run/faults.py injects them)."""

    robots: list[str] | None = Field(None, min_length=1, description="the robots it hits (default: all)")
    start_s: NonNegFloat = Field(0.0, description="active from this simulated time on")
    end_s: PositiveFloat | None = Field(None, description="active before this simulated time (default: to the end)")

    @model_validator(mode="after")
    def _window(self) -> FaultEntry:
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"end_s ({self.end_s:g}) must be after start_s ({self.start_s:g})")
        return self

    def hits(self, robot: str, t: float) -> bool:
        """Whether the fault applies to ``robot`` at time ``t``."""
        return (self.robots is None or robot in self.robots) and self.start_s <= t and (self.end_s is None or t < self.end_s)


class MeasurementFault(FaultEntry):
    """A share of one kind of loop-closure measurement replaced by wrong ones (thesis 4.2.3: overconfident,
    erroneous loop closures)."""

    rate: float = Field(..., ge=0, le=1, description="share of the robot's measurements of this kind replaced, 0..1")
    translation_m: NonNegFloat = Field(1.0, description="the wrong transform's translation error")
    rotation_deg: float = Field(20.0, ge=0, le=180, description="the wrong transform's rotation error")


class WrongDetectionFault(MeasurementFault):
    """A robot detection or landmark observation (thesis 6.2.1) replaced by a wrong one, as a misread tag or a
    mirrored PnP solution gives: the measured transform turned by ``rotation_deg`` about a random axis and moved
    by ``translation_m`` in a random direction, before the robot uses or sends it; its covariance stays."""

    type: Literal["wrong_detection"] = Field(..., description="the fault's kind")


class WrongMatchFault(MeasurementFault):
    """Perceptual aliasing in submap matching (thesis 6.1): a match attempt, whatever the matcher found, yields a
    loop closure at the graph's prediction of the pair turned by ``rotation_deg`` about the vertical and moved
    by ``translation_m`` horizontally (what a 4D match can be wrong by), with a confident covariance, as a wrong
    match that passed RANSAC and ICP would have."""

    type: Literal["wrong_match"] = Field(..., description="the fault's kind")
    sigma_m: PositiveFloat = Field(0.03, description="the wrong closure's translation sigma (an accepted match's ICP RMSE)")
    sigma_deg: PositiveFloat = Field(1.0, description="the wrong closure's rotation sigma")


class DiesFault(FaultEntry):
    """The robot fails for good at ``start_s``: its motors stop (a hexacopter in flight falls), its sensors,
    computer and radio go silent. The rest of the team keeps what it received from it."""

    type: Literal["dies"] = Field(..., description="the fault's kind")

    @model_validator(mode="after")
    def _for_good(self) -> DiesFault:
        if self.end_s is not None:
            raise ValueError("end_s: a robot that dies stays dead (leave end_s out)")
        return self


class CameraDarkFault(FaultEntry):
    """The cameras see nothing (no light reaches the sensor: a lens cap, a dead illumination, a cable): the
    images carry only the sensor's noise."""

    type: Literal["camera_dark"] = Field(..., description="the fault's kind")
    rigs: list[str] | None = Field(None, min_length=1, description="the stereo rigs that go dark (default: all of the robot's)")


class ImuStuckFault(FaultEntry):
    """The IMU repeats its last sample (a frozen driver or bus)."""

    type: Literal["imu_stuck"] = Field(..., description="the fault's kind")


class ImuSaturationFault(FaultEntry):
    """The IMU's range shrinks (a wrong range setting, an overload): each axis clips at the limits. The
    defaults are below lunar gravity (1.62 m/s^2) and a rover's turn rate, so the vertical axis and turns clip."""

    type: Literal["imu_saturation"] = Field(..., description="the fault's kind")
    accel_limit_mps2: PositiveFloat = Field(1.0, description="each accelerometer axis clips at +- this")
    gyro_limit_dps: PositiveFloat = Field(5.0, description="each gyro axis clips at +- this")


class EncoderFailureFault(FaultEntry):
    """One wheel's encoder reads zero speed (a broken encoder or cable); the wheel odometry gets the zero, and its
    encoder check leaves the wheel out where the others outvote it."""

    type: Literal["encoder_failure"] = Field(..., description="the fault's kind")
    wheel: str = Field("fl", description=f"the wheel whose encoder fails; wheels per preset: {_per_preset('wheel_names')}")


class RadioSilentFault(FaultEntry):
    """The robot's radio neither sends nor receives (every link to and from it is down)."""

    type: Literal["radio_silent"] = Field(..., description="the fault's kind")


class ComputeSlowdownFault(FaultEntry):
    """The on-board computer slows down (thermal throttling, a runaway process): every job's compute time
    is multiplied by ``factor``."""

    type: Literal["compute_slowdown"] = Field(..., description="the fault's kind")
    factor: float = Field(4.0, ge=1, le=1000, description="compute time multiplier")


FaultConfig = Annotated[
    WrongDetectionFault
    | WrongMatchFault
    | DiesFault
    | CameraDarkFault
    | ImuStuckFault
    | ImuSaturationFault
    | EncoderFailureFault
    | RadioSilentFault
    | ComputeSlowdownFault,
    Field(discriminator="type"),
]
#: Short forms of a fault entry's keys: ``{kind: dies, robot: lru2, at_s: 10}``.
FAULT_SHORT_KEYS = {"kind": "type", "at_s": "start_s"}


def control_ticks(control_rate_hz: float, rate_hz: float) -> int | None:
    """Control ticks per sample of a sensor at ``rate_hz`` (sensors sample on the control tick); None when the
    rate does not divide the control rate."""
    ticks = control_rate_hz / rate_hz
    if abs(ticks - round(ticks)) > 1e-6 * ticks or round(ticks) < 1:
        return None
    return round(ticks)


class Scenario(StrictModel):
    name: str = Field(..., pattern=r"^[A-Za-z0-9_.-]+$", description="run name; results go to `results/<name>-seed<seed>/`")
    description: str = Field("", description="free text about the scenario (the run does not use it)")
    seed: int = Field(0, ge=0, description="seed of the run's named random streams (terrain, sensor noise, calibration errors, faults, network)")
    duration_s: float = Field(
        ...,
        gt=0,
        le=2 * 86400,
        description="simulated time the run lasts, the drain included",
        json_schema_extra={"why": "at most two days: runs go at about real time, the thesis's longest took an hour"},
    )
    drain_s: NonNegFloat = Field(
        120.0,
        description="once every route is done: the robots rest, sensors off, for up to this long (within duration_s) while "
        "the last submaps are matched and queued jobs and messages finish; ends as soon as none is left",
    )
    terrain: TerrainConfig = Field(TerrainConfig(), description="the ground: heightfield, craters, slope, ridges, rocks, lander, albedo")
    robots: list[RobotConfig] = Field(..., min_length=1, description="the team: at least one robot, names unique")
    physics: PhysicsConfig = Field(PhysicsConfig(), description="MuJoCo time step and control rate")
    compute: ComputeConfig = Field(ComputeConfig(), description="compute time of each on-board job on the robots' scheduler lanes (thesis 8.4)")
    output: OutputConfig = Field(OutputConfig(), description="optional outputs: rerun recording and PNG plots")
    comms: CommsConfig = Field(CommsConfig(), description="the network between robots, lander and ground station (docs/comms.md)")
    slam: SlamConfig = Field(SlamConfig(), description="the on-board estimation stack of every robot (thesis ch. 4-6)")
    realism: RealismConfig = Field(RealismConfig(), description="how far the simulated world departs from the ideal one (docs/realism.md)")
    exploration: ExplorationConfig | None = Field(
        None, description="autonomous frontier exploration of a target region by the team (thesis 9.3; docs/exploration.md); null: none"
    )
    faults: list[FaultConfig] = Field(
        [],
        description="injected failures, each a typed entry (`type:` wrong_detection, wrong_match, dies, camera_dark, imu_stuck, "
        "imu_saturation, encoder_failure, radio_silent, compute_slowdown) with `robots` and a window `start_s`, `end_s`",
    )

    def network_nodes(self) -> list[str]:
        """Nodes of the network: the robots, the lander if there is one, and what the
        comms section adds (a ground station)."""
        nodes = [r.name for r in self.robots]
        if self.terrain.lander is not None:
            nodes.append("lander")
        return nodes + self.comms.extra_nodes()

    def keep_clear(self) -> list[tuple[XY, float]]:
        """Discs ``(xy, radius)`` that rocks and crater centres keep out of: ``terrain.rocks.clearance_m``
        around every robot start and along the straight legs between its waypoints (the
        terrain adds the lander's, :meth:`TerrainConfig.lander_keep_clear`)."""
        clear = self.terrain.rocks.clearance_m
        discs = []
        for cfg in self.robots:
            discs.append((cfg.start.xy, clear))
            for (x0, y0), (x1, y1), n in self._legs(cfg):
                discs += [((x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n), clear) for i in range(n + 1)]
        return discs

    def _check_exploration(self) -> None:
        """Exploring robots exist, can explore, map, and the region lies on the terrain."""
        cfg = self.exploration
        if cfg is None:
            return
        names = {r.name: r for r in self.robots}
        unknown = [n for n in cfg.robots or [] if n not in names]
        if unknown:
            raise ValueError(f"exploration.robots: no robot named {', '.join(map(repr, unknown))} (robots: {', '.join(names)})")
        explorers = cfg.explorers(self.robots)
        if not explorers:
            raise ValueError(f"exploration: no robot can explore (presets that can: {_per_preset('explores')})")
        for name in explorers:
            if not PRESETS[names[name].preset].explores:
                preset = names[name].preset
                raise ValueError(f"exploration.robots: robot {name} (preset {preset}) cannot explore (presets that can: {_per_preset('explores')})")
        if not (self.slam.enabled and self.slam.mapping.enabled and self.slam.graph.enabled):
            raise ValueError(
                "exploration chooses goals on the robots' own maps and shares them: "
                "it needs slam.enabled, slam.mapping.enabled and slam.graph.enabled"
            )
        half = self.terrain.size_m / 2
        for i, (x, y) in enumerate(cfg.region):
            if abs(x) > half or abs(y) > half:
                raise ValueError(f"exploration.region.{i}: {[x, y]} lies outside the {self.terrain.size_m:g} m terrain")
        poly = np.asarray(cfg.region, float)
        area = 0.5 * abs(float(np.dot(poly[:, 0], np.roll(poly[:, 1], 1)) - np.dot(poly[:, 1], np.roll(poly[:, 0], 1))))
        if area < cfg.cell_m**2:
            raise ValueError(f"exploration.region: its area {area:.3g} m^2 is smaller than one {cfg.cell_m:g} m cell")

    def _legs(self, robot: RobotConfig) -> list[tuple[XY, XY, int]]:
        """The straight legs of a robot's route, each with the number of steps of at most
        ``clearance_m`` that :meth:`keep_clear` divides it into."""
        clear = self.terrain.rocks.clearance_m
        points = [robot.start.xy] + [w.xy for w in robot.route.waypoints]
        return [(a, b, max(1, int(math.hypot(b[0] - a[0], b[1] - a[1]) / clear))) for a, b in itertools.pairwise(points)]

    @field_validator("comms")
    @classmethod
    def _check_kinds(cls, comms: CommsConfig) -> CommsConfig:
        unknown = sorted(set(comms.kinds) - set(MESSAGE_KINDS))
        if unknown:
            raise ValueError(f"kinds: unknown message kind {', '.join(map(repr, unknown))}; the robots send: {', '.join(MESSAGE_KINDS)}")
        return comms

    @model_validator(mode="after")
    def _check_team(self) -> Scenario:
        names = [r.name for r in self.robots]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"robot names must be unique, repeated: {dupes}")
        half = self.terrain.size_m / 2
        for robot in self.robots:
            points = [("start", robot.start.xy)] + [
                (f"waypoint {i}", w.xy) for i, w in enumerate(robot.route.waypoints)
            ]
            for what, (x, y) in points:
                if abs(x) > half - 1.0 or abs(y) > half - 1.0:
                    raise ValueError(
                        f"robot {robot.name}: {what} {[x, y]} lies outside the terrain "
                        f"(|x|, |y| <= {half - 1.0:g} m for size_m={self.terrain.size_m:g})"
                    )
        ids = self.assigned_tag_ids()
        used: dict[int, str] = {}
        if self.terrain.lander is not None:
            used[self.terrain.lander.tag_id] = "lander"
        for name, tags in ids.items():
            for tag in tags:
                if tag in used:
                    raise ValueError(f"AprilTag id {tag} of robot {name} is already used by {used[tag]}")
                used[tag] = name
        if "lander" in [r.name for r in self.robots]:
            raise ValueError("'lander' is the name of the lander's network node; pick another robot name")
        try:
            self.comms.check_nodes(self.network_nodes())
        except CommsError as exc:
            raise ValueError(str(exc)) from None
        ratio = 1.0 / (self.physics.control_rate_hz * self.physics.timestep_s)
        if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ValueError(
                "physics.control_rate_hz must divide 1/physics.timestep_s "
                f"(got {self.physics.control_rate_hz:g} Hz at {self.physics.timestep_s:g} s)"
            )
        for robot in self.robots:
            for what, rate in [("camera", robot.camera.rate_hz), ("imu", robot.imu.rate_hz), ("wheel_odometry", robot.wheel_odometry.rate_hz)]:
                if control_ticks(self.physics.control_rate_hz, rate) is None:
                    raise ValueError(
                        f"robot {robot.name}: {what}.rate_hz {rate:g} Hz must divide physics.control_rate_hz "
                        f"({self.physics.control_rate_hz:g} Hz): sensors sample on the control tick"
                    )
        return self

    @model_validator(mode="after")
    def _check_run(self) -> Scenario:
        """What the run would otherwise find at set-up: robots placed on the lander or on each
        other, a VO rig a robot lacks, a link time series or keep-clear discs too large, no room
        for rocks."""
        lander = self.terrain.lander
        for i, a in enumerate(self.robots):
            for b in self.robots[i + 1 :]:
                keep = PRESETS[a.preset].body_radius_m + PRESETS[b.preset].body_radius_m
                gap = math.hypot(a.start.xy[0] - b.start.xy[0], a.start.xy[1] - b.start.xy[1])
                if gap < keep:
                    raise ValueError(
                        f"robots {a.name} and {b.name} start {gap:.2f} m apart, inside each other: keep at least {keep:.2f} m "
                        f"between their start.xy (their presets reach {PRESETS[a.preset].body_radius_m:.2g} and "
                        f"{PRESETS[b.preset].body_radius_m:.2g} m from their centres)"
                    )
        for robot in self.robots:
            preset = PRESETS[robot.preset]
            if robot.navigation.pose_source == "estimate" and not (self.slam.enabled and self.slam.mapping.enabled):
                raise ValueError(
                    f"robot {robot.name}: navigation.pose_source: estimate steers by the on-board estimate and plans on its "
                    "obstacle map: it needs slam.enabled and slam.mapping.enabled"
                )
            rig = self.slam.vo_rig or preset.default_vo_rig
            if rig not in preset.stereo_rig_names:
                raise ValueError(
                    f"slam.vo_rig: {rig!r} is not a stereo rig of robot {robot.name} (preset {robot.preset}: {', '.join(preset.stereo_rig_names)})"
                )
            if lander is None:
                continue
            keep = LANDER_RADIUS + preset.body_radius_m
            points = [("start", robot.start.xy)] + [(f"waypoint {i}", w.xy) for i, w in enumerate(robot.route.waypoints)]
            for what, (x, y) in points:
                if math.hypot(x - lander.xy[0], y - lander.xy[1]) < keep:
                    raise ValueError(
                        f"robot {robot.name}: {what} {[x, y]} lies on the lander at {list(lander.xy)} (keep {keep:.2f} m from its centre: "
                        f"its footprint is {LANDER_RADIUS:g} m in radius, preset {robot.preset} reaches {preset.body_radius_m:.2g} m)"
                    )
        half = self.terrain.size_m / 2
        for n, rock in enumerate(self.terrain.rocks.placed):
            if max(abs(rock.xy[0]), abs(rock.xy[1])) + ROCK_MAX_REACH_FACTOR * rock.diameter_m / 2 > half - 0.1:
                raise ValueError(
                    f"terrain.rocks.placed.{n}: a {rock.diameter_m:g} m rock at {list(rock.xy)} reaches off the {self.terrain.size_m:g} m terrain"
                )
            for robot in self.robots:
                keep = PRESETS[robot.preset].body_radius_m + rock.diameter_m / 2
                if math.hypot(rock.xy[0] - robot.start.xy[0], rock.xy[1] - robot.start.xy[1]) < keep:
                    raise ValueError(f"terrain.rocks.placed.{n}: the rock at {list(rock.xy)} lies on robot {robot.name}'s start (keep {keep:.2f} m)")
            if lander is not None and math.hypot(rock.xy[0] - lander.xy[0], rock.xy[1] - lander.xy[1]) < LANDER_RADIUS + rock.diameter_m / 2:
                raise ValueError(f"terrain.rocks.placed.{n}: the rock at {list(rock.xy)} lies on the lander at {list(lander.xy)}")
        self._check_exploration()
        samples = self.duration_s / self.comms.stats_interval_s
        if samples > MAX_LINK_SAMPLES:
            raise ValueError(
                f"duration_s / comms.stats_interval_s is {samples:.0f} samples of the link time series, at most {MAX_LINK_SAMPLES} "
                f"(memory): raise comms.stats_interval_s to >= {self.duration_s / MAX_LINK_SAMPLES:.3g}"
            )
        clear = self.terrain.rocks.clearance_m
        discs = len(self.robots) + sum(n + 1 for robot in self.robots for _, _, n in self._legs(robot))
        if discs > MAX_KEEP_CLEAR_DISCS:
            raise ValueError(
                f"terrain.rocks.clearance_m={clear:g}: the routes need {discs} keep-clear discs (one every clearance_m along each leg), "
                f"at most {MAX_KEEP_CLEAR_DISCS}: raise clearance_m or shorten the routes"
            )
        if (self.terrain.rocks.count or self.terrain.craters.count) and not self._room_outside(self.keep_clear() + self.terrain.lander_keep_clear()):
            raise ValueError(
                f"terrain.rocks.clearance_m={clear:g}: no room for rocks or craters: the keep-clear discs ({clear:g} m around the robot "
                f"starts and route legs, {LANDER_RADIUS + clear:g} m around a lander) cover the whole terrain; lower clearance_m, "
                "or set rocks.count and craters.count to 0"
            )
        return self

    def _room_outside(self, discs: list[tuple[XY, float]], samples: int = 64) -> bool:
        """Whether some point of the terrain may lie outside every disc: true for a grid point
        closer to the free region than half a grid diagonal, so no room is ever missed."""
        half = self.terrain.size_m / 2
        grid = np.linspace(-half, half, samples)
        slack = (grid[1] - grid[0]) / math.sqrt(2)
        points = np.stack(np.meshgrid(grid, grid), axis=-1).reshape(-1, 2)
        free = np.ones(len(points), bool)
        for start in range(0, len(discs), 256):
            chunk = discs[start : start + 256]
            centres = np.array([xy for xy, _ in chunk], float)
            radii = np.array([r for _, r in chunk], float)
            dist = np.hypot(points[:, None, 0] - centres[None, :, 0], points[:, None, 1] - centres[None, :, 1])
            free &= (dist > radii - slack).all(axis=1)
        return bool(free.any())

    @field_validator("faults", mode="before")
    @classmethod
    def _fault_short_forms(cls, value: Any) -> Any:
        """Accept ``kind`` for ``type``, ``at_s`` for ``start_s`` and ``robot: name`` for ``robots: [name]``."""
        if not isinstance(value, list):
            return value
        out = []
        for item in value:
            if isinstance(item, dict):
                item = dict(item)
                for short, key in [*FAULT_SHORT_KEYS.items(), ("robot", "robots")]:
                    if short in item:
                        if key in item:
                            raise ValueError(f"give `{key}` or its short form `{short}`, not both")
                        short_value = item.pop(short)
                        item[key] = [short_value] if short == "robot" else short_value
            out.append(item)
        return out

    @model_validator(mode="after")
    def _check_faults(self) -> Scenario:
        names = [r.name for r in self.robots]
        for i, fault in enumerate(self.faults):
            unknown = [n for n in fault.robots or [] if n not in names]
            if unknown:
                raise ValueError(f"faults.{i} ({fault.type}): robots: no robot named {', '.join(map(repr, unknown))}; robots: {names}")
            hit = [r for r in self.robots if fault.robots is None or r.name in fault.robots]
            if isinstance(fault, EncoderFailureFault):
                wheeled = [r for r in hit if fault.wheel in PRESETS[r.preset].wheel_names]
                if (fault.robots is not None and len(wheeled) < len(hit)) or not wheeled:
                    raise ValueError(
                        f"faults.{i} (encoder_failure): wheel {fault.wheel!r} is not a wheel of "
                        f"{', '.join(r.name for r in hit if r not in wheeled) or 'any robot'}; wheels per preset: {_per_preset('wheel_names')}"
                    )
            if isinstance(fault, CameraDarkFault) and fault.rigs is not None:
                for r in hit:
                    missing = [rig for rig in fault.rigs if rig not in PRESETS[r.preset].stereo_rig_names]
                    if missing:
                        raise ValueError(
                            f"faults.{i} (camera_dark): rigs {missing} are not stereo rigs of {r.name}; "
                            f"its rigs: {list(PRESETS[r.preset].stereo_rig_names)}"
                        )
        return self

    def assigned_tag_ids(self) -> dict[str, list[int]]:
        """Marker ids per robot: explicit ``tag_ids`` or the next free ids from 1 up."""
        taken = {t for r in self.robots if r.tag_ids for t in r.tag_ids}
        if self.terrain.lander is not None:
            taken.add(self.terrain.lander.tag_id)
        next_id = 1
        out: dict[str, list[int]] = {}
        for robot in self.robots:
            if robot.tag_ids is not None:
                out[robot.name] = list(robot.tag_ids)
                continue
            ids = []
            while len(ids) < robot.marker_count:
                if next_id not in taken:
                    ids.append(next_id)
                    taken.add(next_id)
                next_id += 1
            out[robot.name] = ids
        return out

    def robot(self, name: str) -> RobotConfig:
        for r in self.robots:
            if r.name == name:
                return r
        raise KeyError(f"no robot named {name!r}; robots: {[r.name for r in self.robots]}")


# --------------------------------------------------------------------------- loading


def apply_overrides(raw: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``dotted.key=value`` overrides (values parsed as YAML, :func:`sim.safe_yaml.load`) to a raw scenario.

    List elements are addressed by index, by name for lists of named items such as
    ``robots`` (``robots.lru1.route.speed_mps=0.4``), or all at once with ``*``
    (``robots.*.camera.rate_hz=10``).
    """
    for item in overrides:
        if "=" not in item:
            raise ScenarioError("--set", [f"{item!r}: expected dotted.key=value"])
        key, text = item.split("=", 1)
        try:
            value = safe_yaml.load(text)
        except safe_yaml.YamlError as exc:
            raise ScenarioError("--set", [f"{_shown(item)}: {exc}"]) from None
        parts = key.strip().split(".")
        if not all(parts):
            raise ScenarioError("--set", [f"{_shown(item)}: expected dotted.key=value, the key {key.strip()!r} has an empty part"])
        _set(raw, parts, value, [])
    return raw


def _set(node: Any, parts: list[str], value: Any, done: list[str]) -> None:
    part, rest = parts[0], parts[1:]
    where = ".".join(done + [part])
    if isinstance(node, list):
        indices = range(len(node)) if part == "*" else [_list_index(node, part, where)]
        for index in indices:
            if rest:
                _set(node[index], rest, value, done + [str(index)])
            else:
                node[index] = value
    elif isinstance(node, dict):
        if not rest:
            node[part] = value
            return
        if node.get(part) is None:
            node[part] = {}
        _set(node[part], rest, value, done + [part])
    else:
        raise ScenarioError("--set", [f"{where}: cannot descend into {type(node).__name__} value {node!r}"])


def _list_index(node: list, part: str, where: str) -> int:
    if part.lstrip("-").isdigit():
        index = int(part)
        if not -len(node) <= index < len(node):
            raise ScenarioError("--set", [f"{where}: index {index} out of range (list has {len(node)} items)"])
        return index
    for i, element in enumerate(node):
        if isinstance(element, dict) and element.get("name") == part:
            return i
    names = [e.get("name") for e in node if isinstance(e, dict)]
    raise ScenarioError("--set", [f"{where}: no element named {part!r}; names: {names}"])


def _allowed_keys(model: type[BaseModel], loc: tuple) -> list[str] | None:
    """Walk the schema along ``loc`` (minus its last element) and list the allowed keys there."""
    current: Any = model
    annotation: Any = None
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        if not (isinstance(current, type) and issubclass(current, BaseModel)):
            return None
        field = current.model_fields.get(part)
        if field is None:  # the tag of a discriminated union's member, e.g. faults.0.wrong_match
            current = _inner_model(annotation, tag=part)
            continue
        annotation = field.annotation
        current = _inner_model(annotation)
    if isinstance(current, type) and issubclass(current, BaseModel):
        return sorted(current.model_fields)
    return None


def _inner_model(annotation: Any, tag: str | None = None) -> Any:
    """The (first) model in ``annotation``; with ``tag``, the union member whose ``type`` is that literal."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        kind = annotation.model_fields.get("type")
        if tag is None or (kind is not None and tag in getattr(kind.annotation, "__args__", ())):
            return annotation
        return None
    for arg in getattr(annotation, "__args__", ()) or ():
        found = _inner_model(arg, tag)
        if found is not None:
            return found
    return None


def _bound_reason(loc: tuple) -> str | None:
    """Why the key at ``loc`` is bounded: the ``why`` of its ``json_schema_extra``, if it has one."""
    current: Any = Scenario
    info = None
    for part in loc:
        fields = current.model_fields if isinstance(current, type) and issubclass(current, BaseModel) else {}
        if isinstance(part, str) and part in fields:
            info = fields[part]
            current = _inner_model(info.annotation)
    if info is None:
        return None

    def metadata(annotation: Any) -> list[Any]:
        return [*getattr(annotation, "__metadata__", ()), *(m for arg in typing.get_args(annotation) for m in metadata(arg))]

    for source in (info, *metadata(info.annotation)):
        extra = getattr(source, "json_schema_extra", None)
        if isinstance(extra, dict) and "why" in extra:
            return str(extra["why"])
    return None


def _format_loc(loc: tuple, raw: dict[str, Any]) -> str:
    out: list[str] = []
    node: Any = raw
    for part in loc:
        if isinstance(part, int):
            label = str(part)
            if isinstance(node, list) and part < len(node) and isinstance(node[part], dict) and "name" in node[part]:
                label = f"{part}({node[part]['name']})"
            out.append(label)
            node = node[part] if isinstance(node, list) and part < len(node) else None
        else:
            if part in ("function-after", "function-before") or "[" in str(part):
                continue
            if isinstance(node, dict) and part not in node and node.get("type") == part:
                continue  # pydantic names the member of a discriminated union (faults) by its tag
            out.append(str(part))
            node = node.get(part) if isinstance(node, dict) else None
    return ".".join(out) or "(top level)"


def _describe(error: dict, raw: dict[str, Any]) -> str:
    loc = tuple(error["loc"])
    path = _format_loc(loc, raw)
    if error["type"] == "extra_forbidden":
        allowed = _allowed_keys(Scenario, loc)
        hint = f"; allowed keys here: {', '.join(allowed)}" if allowed else ""
        return f"{path}: unknown key{hint}"
    if error["type"] == "missing":
        return f"{path}: required key is missing"
    if error["type"] == "union_tag_not_found":
        return f"{path}: required key `{error['ctx']['discriminator'].strip(chr(39))}` is missing"
    value = error.get("input")
    msg = error["msg"].removeprefix("Value error, ")
    if isinstance(value, bool) and error["type"] in ("int_type", "float_type"):
        msg += " (true and false are no numbers)"
    if error["type"] in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        why = _bound_reason(loc)
        msg += f": {why}" if why else ""
    if isinstance(value, dict):  # a check across several keys: the message names them (one line each)
        return "\n".join(f"{path}: {line}" for line in msg.splitlines())
    return f"{path}: got {_shown(value)}: {msg}"


def _shown(value: Any) -> str:
    """``repr(value)``, cut to 80 characters."""
    shown = repr(value)
    return shown[:77] + "..." if len(shown) > 80 else shown


def load_scenario(source: str | Path | dict, overrides: list[str] | None = None, base_dir: str | Path | None = None) -> Scenario:
    """Load, override and validate a scenario; raise :class:`ScenarioError` on any problem.
    Relative file paths in it (``comms`` link traces) are taken from ``base_dir``: by
    default the scenario file's folder, or the current directory for a dict."""
    if isinstance(source, dict):
        raw, label = copy.deepcopy(source), "<dict>"  # overrides must not change the caller's dict
    else:
        path = Path(source)
        base_dir = path.parent if base_dir is None else base_dir
        label = str(path)
        if not path.is_file():
            raise ScenarioError(label, ["is a directory, not a YAML file" if path.is_dir() else "file not found"])
        try:
            raw = safe_yaml.load(path)
        except safe_yaml.YamlError as exc:
            raise ScenarioError(label, [str(exc)]) from None
        if not isinstance(raw, dict):
            raise ScenarioError(label, [f"top level must be a mapping, got {type(raw).__name__}"])
    raw = apply_overrides(raw, overrides or [])
    try:
        return Scenario.model_validate(raw, context={"base_dir": base_dir})
    except ValidationError as exc:
        raise ScenarioError(label, [line for e in exc.errors() for line in _describe(e, raw).splitlines()]) from None


def dump_scenario(scenario: Scenario) -> str:
    """The resolved scenario (all defaults filled in) as YAML."""
    data = scenario.model_dump(mode="json")
    ids = scenario.assigned_tag_ids()
    for robot in data["robots"]:
        robot["tag_ids"] = ids[robot["name"]]
    return yaml.safe_dump(data, sort_keys=False)
