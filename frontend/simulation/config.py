"""Configuration of the simulated city traverse: every tunable is a pydantic field.

Units are SI (metres, seconds, radians unless a name ends in ``_deg``). Colours are linear RGB
triples in [0, 1]. Load a YAML/JSON mapping with ``SimulationConfig.model_validate(d)`` or
``SimulationConfig.from_yaml(path)``; a bad value raises pydantic's ``ValidationError``, whose
message names the offending field (``route.speed_mps``, ``appearance_schedule``, ...).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

from frontend.errors import FrontendInputError
from ssmvpr_common.settings_model import SettingsModel

RGB = tuple[float, float, float]
ROUTE_PRESETS = ("block_grid", "figure_eight")


class _Model(SettingsModel):
    """The shared policy, frozen: a city and route built from these settings must not change under them."""

    model_config = ConfigDict(frozen=True)


def _ordered_pair(value: tuple[float, float], name: str) -> tuple[float, float]:
    if value[0] > value[1]:
        raise ValueError(f"{name} must be (low, high) with low <= high, got {value}")
    return value


class CityConfig(_Model):
    """Streets laid along the route's centre line; districts of different character line them.

    ``block_size_m`` and ``street_width_m`` also set the grid the preset routes drive on.
    District kinds: ``dense`` (tall facades, shops, parked cars), ``suburban`` (houses set
    back behind hedges and front-garden trees), ``open`` (fields and parkland: trees and
    poles only) and ``highway`` (guard rails and poles). Which one a place belongs to is a
    smooth function of position (``district_scale_m``), so every visit sees the same district.
    """

    block_size_m: float = Field(60.0, gt=5.0, description="block edge of the preset route grid")
    street_width_m: float = Field(16.0, gt=4.0, description="plot line to plot line")
    sidewalk_width_m: float = Field(2.5, ge=0.0, description="sidewalk on each side, within street_width_m")
    district_mix: dict[Literal["dense", "suburban", "open", "highway"], float] = Field(
        default={"dense": 0.45, "suburban": 0.3, "open": 0.15, "highway": 0.1},
        description="share of the route's length in each district kind",
    )
    district_scale_m: float = Field(120.0, gt=1.0, description="size of a district along the route")
    side_street_probability: float = Field(0.12, ge=0.0, le=1.0, description="a side street after a building")
    side_street_width_range_m: tuple[float, float] = Field(
        (9.0, 13.0), description="gap a side street leaves after a building"
    )
    house_width_range_m: tuple[float, float] = Field((8.0, 12.0), description="frontage of a suburban house")
    house_setback_range_m: tuple[float, float] = Field((3.0, 7.0), description="suburban house facade behind plot line")
    house_storeys_range: tuple[int, int] = Field(
        (1, 2), description="storeys of a suburban house above its ground floor"
    )
    house_gap_probability: float = Field(0.6, ge=0.0, le=1.0, description="a gap with a tree after a suburban house")
    hedge_probability: float = Field(0.5, ge=0.0, le=1.0, description="suburban plot has a front hedge")
    tree_spacing_range_m: tuple[float, float] = Field(
        (8.0, 30.0), description="step between tree sites on open roads (x1.5 on highways)"
    )
    tree_crown_size_range_m: tuple[float, float] = Field((3.0, 6.0), description="width of a tree's square crown")
    tree_height_range_m: tuple[float, float] = Field((5.0, 10.0), description="height of a tree")
    guard_rail_height_m: float = Field(0.75, gt=0.0, description="height of highway guard rails")
    road_camber: float = Field(0.02, ge=0.0, lt=0.2, description="fall of the road from its crown, per metre")
    kerb_height_m: float = Field(0.12, ge=0.0, description="sidewalks and verges above the road edge")
    verge_relief_m: float = Field(0.4, ge=0.0, description="peak undulation of the ground beyond the street")
    facade_relief_probability: float = Field(0.7, ge=0.0, le=1.0, description="facade has piers and recessed bays")
    facade_relief_depth_range_m: tuple[float, float] = Field(
        (0.2, 0.6), description="depth of a relief facade's recessed bays"
    )
    facade_bay_width_range_m: tuple[float, float] = Field(
        (3.0, 6.0), description="approximate width of a relief facade's bays"
    )
    building_width_range_m: tuple[float, float] = Field(
        (8.0, 16.0), description="frontage of a dense-district building"
    )
    building_depth_m: float = Field(10.0, gt=1.0, description="length of the side walls")
    setback_range_m: tuple[float, float] = Field((0.0, 2.5), description="facade behind plot line")
    storey_height_range_m: tuple[float, float] = Field(
        (3.0, 3.8), description="height of each storey above the ground floor"
    )
    ground_floor_height_range_m: tuple[float, float] = Field(
        (3.6, 4.6), description="height of a building's ground floor"
    )
    storeys_range: tuple[int, int] = Field(
        (2, 7), description="storeys of a dense-district building above its ground floor"
    )
    parapet_m: float = Field(0.6, ge=0.0, description="height of the cornice band above the top storey")
    gap_probability: float = Field(0.15, ge=0.0, le=1.0, description="alley after a building")
    gap_width_range_m: tuple[float, float] = Field(
        (2.0, 4.0), description="alley between dense buildings (suburban gaps: twice this)"
    )
    alley_depth_m: float = Field(8.0, gt=0.0, description="alley back wall behind the facade")
    pole_spacing_m: float = Field(15.0, gt=1.0, description="lamp posts along each kerb")
    pole_jitter_m: float = Field(3.0, ge=0.0, description="random change of each pole spacing, within ± half this")
    pole_size_m: float = Field(0.35, gt=0.0, description="side of a pole's square section")
    pole_height_m: float = Field(5.5, gt=0.0, description="height of lamp posts")
    pole_kerb_offset_m: float = Field(0.6, ge=0.0, description="pole centre behind the kerb")
    parked_car_probability: float = Field(
        0.3, ge=0.0, le=1.0, description="a kerb slot holds a car (re-drawn every parked_car_turnover_s)"
    )
    car_slot_length_m: float = Field(7.0, gt=1.0, description="kerb length per parked-car slot")
    car_size_m: tuple[float, float, float] = Field((4.3, 1.8, 1.5), description="length width height")
    car_kerb_gap_m: float = Field(0.3, ge=0.0, description="gap between a parked car and the kerb")
    facade_palette: list[RGB] = Field(
        default=[
            (0.62, 0.30, 0.22),  # brick red
            (0.80, 0.72, 0.58),  # sandstone
            (0.62, 0.62, 0.60),  # concrete grey
            (0.88, 0.86, 0.80),  # white render
            (0.55, 0.66, 0.74),  # pale blue
            (0.78, 0.60, 0.30),  # ochre
            (0.42, 0.32, 0.26),  # dark brown
            (0.60, 0.70, 0.55),  # sage green
        ],
        min_length=1,
        description="base colours of the facades",
    )
    accent_palette: list[RGB] = Field(
        default=[
            (0.85, 0.12, 0.10),
            (0.10, 0.35, 0.80),
            (0.95, 0.75, 0.10),
            (0.10, 0.60, 0.30),
            (0.60, 0.15, 0.60),
            (0.95, 0.45, 0.10),
        ],
        min_length=1,
        description="signs, awnings, doors, parked cars",
    )
    colour_jitter: float = Field(0.06, ge=0.0, description="per-facade random change of the base colour")
    sign_probability: float = Field(0.45, ge=0.0, le=1.0, description="ground floor has a shop sign (not houses)")
    awning_probability: float = Field(0.3, ge=0.0, le=1.0, description="shop front has an awning (not houses)")
    shop_probability: float = Field(0.6, ge=0.0, le=1.0, description="glazed ground floor")
    window_spacing_range_m: tuple[float, float] = Field((2.0, 3.6), description="window pitch along a facade")
    window_width_fraction_range: tuple[float, float] = Field(
        (0.35, 0.7), description="window width, fraction of the window pitch"
    )
    window_height_fraction_range: tuple[float, float] = Field(
        (0.4, 0.65), description="window height, fraction of the storey height"
    )
    sign_length_range_m: tuple[float, float] = Field((3.0, 8.0), description="length of a shop sign")
    sign_offset_range_m: tuple[float, float] = Field((0.5, 6.0), description="start of the shop sign along the facade")
    door_offset_range_m: tuple[float, float] = Field((1.0, 6.0), description="door position along the facade")

    @field_validator(
        "building_width_range_m",
        "setback_range_m",
        "storey_height_range_m",
        "ground_floor_height_range_m",
        "gap_width_range_m",
        "window_spacing_range_m",
        "window_width_fraction_range",
        "window_height_fraction_range",
        "sign_length_range_m",
        "sign_offset_range_m",
        "door_offset_range_m",
        "side_street_width_range_m",
        "house_width_range_m",
        "house_setback_range_m",
        "tree_spacing_range_m",
        "tree_crown_size_range_m",
        "tree_height_range_m",
        "facade_relief_depth_range_m",
        "facade_bay_width_range_m",
    )
    @classmethod
    def _check_pair(cls, v, info):
        if v[0] <= 0 and info.field_name != "setback_range_m":
            raise ValueError(f"{info.field_name} must be positive, got {v}")
        return _ordered_pair(v, info.field_name)

    @field_validator("district_mix")
    @classmethod
    def _check_mix(cls, v):
        if not v or any(w < 0 for w in v.values()) or sum(v.values()) <= 0:
            raise ValueError(f"district_mix needs non-negative shares with a positive sum, got {v}")
        return v

    @field_validator("storeys_range", "house_storeys_range")
    @classmethod
    def _check_storeys(cls, v):
        if v[0] < 1:
            raise ValueError(f"storeys ranges must start at 1 or more, got {v}")
        return _ordered_pair(v, "storeys range")

    @model_validator(mode="after")
    def _check_street(self):
        if 2 * self.sidewalk_width_m >= self.street_width_m:
            raise ValueError("sidewalk_width_m leaves no road inside street_width_m")
        return self

    @property
    def pitch_m(self) -> float:
        """Distance between neighbouring street centre lines."""
        return self.block_size_m + self.street_width_m

    @property
    def road_half_width_m(self) -> float:
        return self.street_width_m / 2.0 - self.sidewalk_width_m


class RouteConfig(_Model):
    """Where the vehicle drives. ``preset`` is a named route or a TUM / KITTI poses file."""

    preset: str = Field("block_grid", description="block_grid | figure_eight | path to poses file")
    poses_format: Literal["auto", "tum", "kitti"] = Field(
        "auto", description="format of a poses-file route; auto: detected from its contents"
    )
    poses_frame: Literal["auto", "camera", "body"] = Field(
        "auto", description="camera: KITTI ground truth (x right, y down, z forward); body: x forward, z up"
    )
    file_height_scale: float = Field(1.0, ge=0.0, description="scales a poses file's height profile")
    terrain_amplitude_m: float = Field(2.5, ge=0.0, description="hills of preset routes (peak)")
    terrain_wavelength_m: float = Field(150.0, gt=1.0, description="size of the hills of preset routes")
    speed_mps: float = Field(11.0, gt=0.0, description="cruise speed on straights")
    speed_variation: float = Field(0.08, ge=0.0, lt=0.9, description="relative amplitude")
    speed_variation_period_s: float = Field(25.0, gt=0.0, description="period of the cruise speed's smooth variation")
    max_lateral_accel_mps2: float = Field(3.0, gt=0.0, description="sets the cornering speed")
    max_accel_mps2: float = Field(2.0, gt=0.0, description="speed-profile limit on speeding up")
    max_decel_mps2: float = Field(3.0, gt=0.0, description="speed-profile limit on braking")
    curvature_window_m: float = Field(1.0, gt=0.0, description="smoothing of the path curvature")
    laps: int = Field(2, ge=1, description="laps of the main loop (block_grid, figure_eight)")
    turn_radius_m: float = Field(7.0, gt=0.0, description="corner radius of preset routes")
    lane_offset_m: float = Field(-1.6, description="lateral offset from the centre line, + = left")
    lateral_wander_m: float = Field(0.25, ge=0.0, description="smooth lateral weaving amplitude")
    wander_wavelength_m: float = Field(70.0, gt=0.0, description="wavelength of the lateral weaving (preset routes)")
    path_smoothing_m: float = Field(3.0, ge=0.0, description="gaussian sigma easing turns in and out")
    path_resolution_m: float = Field(0.05, gt=0.0, description="sampling of the dense path")
    file_path_smoothing_m: float = Field(
        2.0, ge=0.0, description="gaussian sigma smoothing a poses file's path (recorded poses jitter)"
    )
    file_heading_smoothing_m: float = Field(2.0, ge=0.0, description="poses-file routes only")
    crossings: list[list[tuple[int, int]]] | None = Field(
        None,
        description="passes of a street-grid route as crossings (i, j), each pass starting where the last ended "
        "(replaces the preset's passes; `laps` is ignored): how sessions of one city take different routes",
    )

    @field_validator("preset")
    @classmethod
    def _check_preset(cls, v: str) -> str:
        if v in ROUTE_PRESETS:
            return v
        if not Path(v).is_file():
            raise ValueError(f"route preset {v!r} is neither a known preset {ROUTE_PRESETS} nor an existing poses file")
        return v

    @field_validator("crossings")
    @classmethod
    def _check_crossings(cls, v: list[list[tuple[int, int]]] | None) -> list[list[tuple[int, int]]] | None:
        if v is None:
            return v
        if not v or any(len(p) < 2 for p in v):
            raise ValueError("crossings: every pass needs at least two crossings")
        for before, after in zip(v, v[1:]):
            if tuple(before[-1]) != tuple(after[0]):
                raise ValueError(f"crossings: a pass starts at {after[0]}, not where the last ended ({before[-1]})")
        for p in v:
            for a, b in zip(p, p[1:]):
                if (a[0] != b[0]) == (a[1] != b[1]):
                    raise ValueError(f"crossings: {a} -> {b} is not along one street of the grid")
        return v

    @property
    def is_file(self) -> bool:
        return self.preset not in ROUTE_PRESETS and self.crossings is None


class CameraConfig(_Model):
    """Forward pinhole camera on the vehicle's vertical axis, looking along body x, and an
    optional identical one looking backwards (along -x)."""

    enabled: bool = Field(True, description="render camera images")
    rear: bool = Field(
        True,
        description="also render a rear camera: at a street driven the other way it sees what the "
        "forward camera saw, so reverse revisits can be recognised",
    )
    width: int = Field(320, ge=8, description="image width in pixels")
    height: int = Field(240, ge=8, description="image height in pixels")
    hfov_deg: float = Field(90.0, gt=1.0, lt=170.0, description="horizontal field of view")
    height_m: float = Field(1.6, gt=0.0, description="above the ground")
    layers: int = Field(3, ge=1, description="nearest walls per column considered (occlusion)")
    max_depth_m: float = Field(400.0, gt=0.0, description="walls farther along the ray are not drawn")
    texture_fade_distance_m: float = Field(90.0, gt=0.0, description="ground detail fades (anti-alias)")


class LidarConfig(_Model):
    """Spinning multi-beam LiDAR; its frame is the body frame the poses describe."""

    enabled: bool = Field(True, description="simulate LiDAR scans")
    beams: int = Field(64, ge=1, description="rings: fewer and sparser ground rings make ICP sticky")
    azimuths: int = Field(1024, ge=8, description="firings per beam in one sweep (points per ring)")
    vfov_deg: tuple[float, float] = Field((-16.6, 16.6), description="uniform beams (an Ouster OS1-64's field)")
    height_m: float = Field(1.8, gt=0.0, description="above the ground (the pose's z)")
    max_range_m: float = Field(80.0, gt=0.0, description="farther returns are dropped")
    min_range_m: float = Field(0.5, ge=0.0, description="nearer returns are dropped")
    range_noise_sigma_m: float = Field(0.02, ge=0.0, description="sigma of the gaussian noise on each range")
    dropout_probability: float = Field(0.0, ge=0.0, lt=1.0, description="a return is lost at random")
    scan_period_s: float | None = Field(None, gt=0.0, description="default: 1 / frame_rate_hz")
    motion_distortion: bool = Field(True, description="each azimuth measured from the pose at its time")
    layers: int = Field(4, ge=1, description="nearest walls per azimuth considered")
    # Errors of a real sensor: fixed per unit (seeded), so every visit shares them.
    beam_elevation_error_deg: float = Field(
        0.08, ge=0.0, description="sigma of each beam's elevation calibration error"
    )
    beam_elevation_bias_deg: float = Field(
        0.0, gt=-5.0, lt=5.0, description="error shared by all beams (KITTI's HDL-64 scans need about 0.22)"
    )
    range_bias_sigma_m: float = Field(0.02, ge=0.0, description="sigma of each beam's constant range offset")
    beam_azimuth_error_deg: float = Field(
        0.15,
        ge=0.0,
        lt=5.0,
        description="sigma of each beam's azimuth (rotational) calibration error; it makes kiss-icp's heading drift",
    )
    range_scale_error: float = Field(0.0, gt=-0.1, lt=0.1, description="relative range error of the unit")
    # Vegetation is porous: a beam may pass a crown or return from anywhere inside it.
    foliage_return_probability: float = Field(
        0.5, ge=0.0, le=1.0, description="a beam meeting a crown or hedge returns from it (else passes)"
    )
    foliage_depth_m: float = Field(1.2, ge=0.0, description="returns spread this deep into a crown")
    # Glass: a beam meeting a window mostly passes it and returns from the room behind.
    glass_pass_probability: float = Field(
        0.6, ge=0.0, le=1.0, description="a beam meeting glass returns from the room behind it"
    )
    glass_dropout_probability: float = Field(0.25, ge=0.0, le=1.0, description="a beam meeting glass returns nothing")

    @field_validator("vfov_deg")
    @classmethod
    def _check_vfov(cls, v):
        if not (-90.0 < v[0] < v[1] < 90.0):
            raise ValueError(f"vfov_deg must be (low, high) inside (-90, 90), got {v}")
        return v


class OdometryDriftConfig(_Model):
    """Error model of the logged ("wheel") odometry, integrated frame to frame."""

    scale_error: float = Field(0.02, gt=-0.5, lt=0.5, description="relative distance error")
    yaw_drift_rad_per_m: float = Field(5e-4, description="constant heading bias")
    yaw_bias_walk_rad_per_m_sqrt_m: float = Field(2e-5, ge=0.0, description="random walk of the bias")
    yaw_noise_rad_per_sqrt_m: float = Field(1e-3, ge=0.0, description="sigma of each step's heading noise")
    translation_noise_m_per_sqrt_m: float = Field(
        0.01, ge=0.0, description="sigma of each step's position noise (x and y)"
    )


class TrafficConfig(_Model):
    """What moves between visits: oncoming vehicles, and parked cars that come and go."""

    oncoming_vehicles_per_km: float = Field(6.0, ge=0.0, description="vehicles on the oncoming lane")
    speed_range_mps: tuple[float, float] = Field((7.0, 14.0), description="speed of each oncoming vehicle")
    oncoming_lane_offset_m: float | None = Field(
        None, description="left of the centre line; default: mirror of the driven lane (preset) or 3.2 m (file)"
    )
    vehicle_size_m: tuple[float, float, float] = Field(
        (4.5, 1.8, 1.5), description="length width height of the oncoming vehicles"
    )
    parked_car_turnover_s: float = Field(
        45.0, gt=0.0, description="each kerb slot is re-drawn this often (own phase), so visits differ"
    )

    @field_validator("speed_range_mps")
    @classmethod
    def _check_speed(cls, v):
        if v[0] <= 0:
            raise ValueError(f"speed_range_mps must be positive, got {v}")
        return _ordered_pair(v, "speed_range_mps")


class AppearanceConfig(_Model):
    """How one pass looks: illumination, colour cast, sensor noise, sky, lit windows."""

    gain: float = Field(1.0, gt=0.0)
    tint: RGB = (1.0, 1.0, 1.0)
    ambient: float = Field(0.55, ge=0.0)
    sun_strength: float = Field(0.45, ge=0.0)
    sun_azimuth_deg: float = 35.0
    noise_sigma: float = Field(3.0, ge=0.0, description="gaussian pixel noise, 8-bit units")
    gamma: float = Field(1.0, gt=0.0)
    sky_top: RGB = (0.35, 0.55, 0.90)
    sky_horizon: RGB = (0.75, 0.85, 0.95)
    fog_distance_m: float = Field(220.0, gt=0.0)
    lit_window_fraction: float = Field(0.0, ge=0.0, le=1.0)
    lit_window_colour: RGB = (1.0, 0.82, 0.45)
    lit_window_strength: float = Field(0.0, ge=0.0)
    foliage_tint: RGB = Field((1.0, 1.0, 1.0), description="season of the leaves")


def _default_appearances() -> dict[str, AppearanceConfig]:
    return {
        "day": AppearanceConfig(),
        "dusk": AppearanceConfig(
            gain=0.7,
            tint=(1.1, 0.85, 0.7),
            ambient=0.6,
            sun_strength=0.25,
            sun_azimuth_deg=200.0,
            noise_sigma=4.0,
            sky_top=(0.30, 0.30, 0.55),
            sky_horizon=(0.95, 0.60, 0.40),
            fog_distance_m=160.0,
            lit_window_fraction=0.2,
            lit_window_strength=0.35,
            foliage_tint=(1.15, 0.85, 0.6),
        ),
        "night": AppearanceConfig(
            gain=0.22,
            tint=(0.8, 0.85, 1.1),
            ambient=0.9,
            sun_strength=0.0,
            noise_sigma=6.0,
            sky_top=(0.01, 0.01, 0.04),
            sky_horizon=(0.06, 0.06, 0.12),
            fog_distance_m=90.0,
            lit_window_fraction=0.35,
            lit_window_strength=0.85,
        ),
    }


class SimulationConfig(_Model):
    """A whole simulated traverse."""

    seed: int = Field(0, ge=0, le=2**32 - 1, description="of every random stream (0 .. 2**32 - 1)")
    frame_rate_hz: float = Field(
        5.0, gt=0.0, description="frames per second (and LiDAR sweeps, unless lidar.scan_period_s)"
    )
    start_time_s: float = Field(0.0, ge=0.0, description="timestamp of the first frame")
    session_seed: int | None = Field(
        None, ge=0, le=2**32 - 1,
        description="seed of what differs between sessions in one city (route weave and speed, traffic, sensor "
        "noise, odometry drift); None: `seed`. The city, its terrain and the sensors' calibration follow `seed`",
    )  # fmt: skip
    city_route: RouteConfig | None = Field(
        None,
        description="the streets the city is laid along (a route covering them all); None: the vehicle's own route. "
        "Sessions of one city share it, so each drives its own route through the same buildings",
    )
    max_frames: int | None = Field(None, ge=1, description="stop early")
    city: CityConfig = CityConfig()
    route: RouteConfig = RouteConfig()
    camera: CameraConfig = CameraConfig()
    lidar: LidarConfig = LidarConfig()
    odometry: OdometryDriftConfig = OdometryDriftConfig()
    traffic: TrafficConfig = TrafficConfig()
    appearances: dict[str, AppearanceConfig] = Field(
        default_factory=_default_appearances, description="named looks (light, colour, noise) appearance_schedule picks"
    )
    appearance_schedule: list[str] = Field(
        default=["day", "day", "dusk"],
        min_length=1,
        description="appearance per pass (loop); the last one repeats. The default is the demo's: the demo city's "
        "loop A twice by day, then loop B at dusk",
    )

    @model_validator(mode="after")
    def _check_schedule(self):
        unknown = [n for n in self.appearance_schedule if n not in self.appearances]
        if unknown:
            raise ValueError(f"appearance_schedule names {unknown} not in appearances {sorted(self.appearances)}")
        return self

    @property
    def scan_period_s(self) -> float:
        return self.lidar.scan_period_s or 1.0 / self.frame_rate_hz

    @classmethod
    def from_yaml(cls, path: str | Path) -> SimulationConfig:
        """Read a YAML mapping; raises FrontendInputError naming the file when unreadable or invalid."""
        import yaml

        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise FrontendInputError(f"simulation config {path}: cannot read: {exc}") from exc
        if not isinstance(data, dict):
            raise FrontendInputError(f"simulation config {path}: expected a mapping at top level")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:  # a bad key or value: name the file and the field
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "(top level)"
            raise FrontendInputError(
                f"simulation config {path}: {where}: {first['msg']} ({exc.error_count()} error(s))"
            ) from None
