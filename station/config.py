"""The station config file (`station.toml`): what this rig is, so nothing rig-specific is fixed in code.

One file describes the rig geometry, the turntable board, the camera, the default plan and where
the calibrated rig model lives; CLI flags override single values. The file is read with the
standard library's tomllib and checked field by field (pydantic over these plain dataclasses), so
a typo or a wrong type is refused with the file and the key named, before any device is opened.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import pydantic
from pydantic import ConfigDict, TypeAdapter, with_config

from station.capture.plan import ScanPlan, default_elevations
from station.errors import BadInputError
from station.rig_geometry import RigGeometry
from station.turntable.grbl import TurntableConfig

CameraBackend = Literal["ptp", "gphoto2", "sim"]
DEFAULT_CAMERA_URL: dict[str, str] = {"ptp": "ptp://usb", "gphoto2": "gphoto2://", "sim": "sim://"}
_STRICT = ConfigDict(extra="forbid")


class ConfigError(BadInputError):
    """The station config file is missing, unreadable, or has a bad key or value."""


@with_config(_STRICT)
@dataclass(frozen=True)
class TurntableSection:
    """The board and what its `$$` settings must say (checked by the driver and `station rig check`)."""

    port: str = ""  # grbl:///dev/ttyUSB0, a device path, or any pyserial URL
    turn_axis: Literal["X"] = "X"
    tilt_axis: Literal["Y", "A"] = "Y"
    steps_per_deg: tuple[float, float] = (44.444, 44.444)  # $100 and $101 (or $103 for A)
    max_rate_deg_min: tuple[float, float] = (3600.0, 1800.0)  # $110, $111
    accel_deg_s2: tuple[float, float] = (180.0, 90.0)  # $120, $121
    max_travel_deg: tuple[float, float] = (720.0, 90.0)  # $130, $131
    soft_limits: bool = False  # $20
    homing: bool = False  # $22
    feed_deg_min: float = 1800.0
    tilt_limits_deg: tuple[float, float] = (0.0, 90.0)
    rotation: Literal["shortest", "continuous"] = "shortest"
    baudrate: int = 115200

    def driver_config(self) -> TurntableConfig:
        """The driver's own config: the values it checks on connect and moves with."""
        return TurntableConfig(
            steps_per_deg=self.steps_per_deg, max_rate_deg_min=self.max_rate_deg_min, accel_deg_s2=self.accel_deg_s2,
            feed_deg_min=self.feed_deg_min, tilt_limits_deg=self.tilt_limits_deg, tilt_axis=self.tilt_axis,
            rotation=self.rotation, baudrate=self.baudrate,
        )

    def expected_settings(self) -> dict[int, float]:
        """GRBL setting number -> the value this rig needs (tilt on Y uses $1x1, on A $1x3)."""
        tilt = {"Y": 1, "A": 3}[self.tilt_axis]
        expected: dict[int, float] = {20: float(self.soft_limits), 22: float(self.homing)}
        for j, axis in enumerate((0, tilt)):
            expected[100 + axis] = self.steps_per_deg[j]
            expected[110 + axis] = self.max_rate_deg_min[j]
            expected[120 + axis] = self.accel_deg_s2[j]
            expected[130 + axis] = self.max_travel_deg[j]
        return expected


@with_config(_STRICT)
@dataclass(frozen=True)
class CameraSection:
    """Which camera and the fixed exposure every frame of a scan shares (manual mode on the body)."""

    backend: CameraBackend = "ptp"
    url: str = ""  # empty: the backend's default (ptp://usb, gphoto2://, sim://)
    exposure_s: float = 1.0 / 30.0
    iso: int = 100
    aperture: float = 0.0  # f-number; 0 leaves the lens as it is
    raw_format: Literal["dng", "cr2", "cr3", "nef", "arw", "raf", "orf", "rw2", "any"] = "dng"

    @property
    def resolved_url(self) -> str:
        return self.url or DEFAULT_CAMERA_URL[self.backend]


@with_config(_STRICT)
@dataclass(frozen=True)
class PlanSection:
    """The default scan: `elevations` evenly spread tilts, or the exact `elevations_deg`."""

    elevations: int = 6
    elevations_deg: tuple[float, ...] = ()
    azimuths: int = 40


@with_config(_STRICT)
@dataclass(frozen=True)
class RigSection:
    """Nominal geometry (metres, pixels of the raw the camera delivers): the prior before calibration."""

    orbit_radius_m: float = 0.45
    aim_height_m: float = 0.04
    width: int = 320
    height: int = 240
    focal_px: float = 560.0

    def geometry(self) -> RigGeometry:
        return RigGeometry(self.orbit_radius_m, self.aim_height_m, self.width, self.height, self.focal_px)


@with_config(_STRICT)
@dataclass(frozen=True)
class StationConfig:
    """Everything `station.toml` holds; `source` names the file in every error and report."""

    rig: RigSection = field(default_factory=RigSection)
    turntable: TurntableSection = field(default_factory=TurntableSection)
    camera: CameraSection = field(default_factory=CameraSection)
    plan: PlanSection = field(default_factory=PlanSection)
    rig_model: str = ""  # path of the calibrated rig model; relative paths are from the config's folder
    source: str = "built-in defaults"

    def scan_plan(self) -> ScanPlan:
        elevations = self.plan.elevations_deg or default_elevations(self.plan.elevations)
        return ScanPlan(elevations_deg=tuple(elevations), azimuths=self.plan.azimuths,
                        exposure_s=self.camera.exposure_s, iso=self.camera.iso)

    def rig_model_path(self) -> Path | None:
        """Where `station calibrate` writes, and `station process` reads, the calibrated rig model."""
        if not self.rig_model:
            return None
        path = Path(self.rig_model).expanduser()
        if not path.is_absolute() and self.source.endswith(".toml"):
            path = Path(self.source).parent / path
        return path

    def with_overrides(self, *, port: str | None = None, camera: str | None = None,
                       elevations: int | None = None, azimuths: int | None = None) -> StationConfig:
        """CLI flags win over the file; `camera` is a backend name or a camera URL."""
        config = self
        if port:
            config = replace(config, turntable=replace(config.turntable, port=port))
        if camera:
            backend = "ptp" if camera == "usb" else camera.split("://")[0]
            if backend not in DEFAULT_CAMERA_URL:
                raise BadInputError(f"--camera {camera!r}: expected usb, ptp, gphoto2, sim or a URL such as gphoto2://")
            url = camera if "://" in camera else ""
            config = replace(config, camera=replace(config.camera, backend=backend, url=url))
        if elevations is not None:
            config = replace(config, plan=replace(config.plan, elevations=elevations, elevations_deg=()))
        if azimuths is not None:
            config = replace(config, plan=replace(config.plan, azimuths=azimuths))
        return config


_ADAPTER = TypeAdapter(StationConfig)


def _key(loc: tuple) -> str:
    """TOML's dotted-key spelling of a location: turntable.steps_per_deg, with list indexes as [1]."""
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")


def parse_config(data: dict, source: str) -> StationConfig:
    """Check a decoded TOML table; the first problem is reported with its section and key."""
    if "source" in data:
        raise ConfigError(f"{source}: unknown key 'source'")
    try:
        config = _ADAPTER.validate_python({**data, "source": source})
    except pydantic.ValidationError as exc:
        problems = []
        for err in exc.errors():
            what = "unknown key" if err["type"] == "unexpected_keyword_argument" else err["msg"]
            given = "" if err["type"] in ("unexpected_keyword_argument", "missing") else f" (got {err['input']!r})"
            problems.append(f"{_key(err['loc'])}: {what}{given}")
        raise ConfigError(f"{source}: " + "; ".join(problems)) from None
    except BadInputError as exc:  # a value the driver or the plan refuses
        raise ConfigError(f"{source}: {exc}") from None
    _check_values(config)
    return config


def _check_values(config: StationConfig) -> None:
    src, cam, table, rig = config.source, config.camera, config.turntable, config.rig
    checks = [
        (cam.exposure_s > 0, "camera.exposure_s must be positive"),
        (cam.iso > 0, "camera.iso must be positive"),
        (cam.aperture >= 0, "camera.aperture must be an f-number, or 0 to leave the lens as it is"),
        (all(v > 0 for v in table.steps_per_deg), "turntable.steps_per_deg must be positive"),
        (all(v > 0 for v in table.max_rate_deg_min), "turntable.max_rate_deg_min must be positive"),
        (all(v > 0 for v in table.accel_deg_s2), "turntable.accel_deg_s2 must be positive"),
        (all(v > 0 for v in table.max_travel_deg), "turntable.max_travel_deg must be positive"),
        (table.feed_deg_min > 0, "turntable.feed_deg_min must be positive"),
        (rig.width >= 16 and rig.height >= 16 and rig.width % 2 == 0 and rig.height % 2 == 0,
         "rig.width and height must be even and at least 16 pixels"),
        (rig.orbit_radius_m > 0 and rig.focal_px > 0, "rig.orbit_radius_m and focal_px must be positive"),
        (config.plan.elevations >= 1 and config.plan.azimuths >= 1, "plan.elevations and azimuths must be >= 1"),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(f"{src}: {message}")
    try:
        table.driver_config()
        config.scan_plan()
    except BadInputError as exc:
        raise ConfigError(f"{src}: {exc}") from None


def load_config(path: Path | None) -> StationConfig:
    """The config at `path`, or the built-in defaults when no file is given."""
    if path is None:
        return StationConfig()
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse_config(data, str(path))
