"""The instrument config: one YAML file, pydantic models, unknown keys rejected.

A bad config fails at load with the file, the key path and the reason (``ConfigError``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from alignd.errors import ConfigError
from drivers.config import CameraConfig, ControllerConfig, SimConfig


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HolderConfig(Strict):
    """Geometry of the sample holder as the top camera sees it (holder frame, mm).

    Holder frame: origin at the centre of the four tracked corners, u along the first
    corner edge (corner 0 -> corner 1), v perpendicular (towards corner 3). The target is
    the middle of the sample surface; the sample normal points from the holder to it.
    """

    size_mm: tuple[float, float] = (60.0, 40.0)
    target_mm: tuple[float, float] = (0.0, -25.0)


class SideCameraConfig(Strict):
    """Where the side camera sees its targets (px, x0, y0, x1, y1; x1/y1 exclusive).

    Leave both unset for the automatic mode (the pole is the narrow bar running through
    the image height, the sample edge the nearest other long straight edge); set them when
    the scene has other long edges (a holder, a platform, a background frame) or the pole
    is not the narrowest bar. Angles are from the image vertical, positive when a line's
    top leans toward +x (clockwise on screen, as the top camera's angles); tilt = sample -
    pole.
    """

    pole_roi_px: tuple[int, int, int, int] | None = None
    sample_roi_px: tuple[int, int, int, int] | None = None

    @model_validator(mode="after")
    def _boxes(self) -> SideCameraConfig:
        for key, box in (("pole_roi_px", self.pole_roi_px),
                         ("sample_roi_px", self.sample_roi_px)):
            if box is not None and not (0 <= box[0] < box[2] and 0 <= box[1] < box[3]):
                raise ValueError(f"{key}: expected [x0, y0, x1, y1] with 0 <= x0 < x1 and "
                                 f"0 <= y0 < y1, got {list(box)}")
        return self


class PrecheckConfig(Strict):
    max_eccentricity: float = Field(0.05, gt=0, lt=1)
    max_tilt_deg: float = Field(0.5, gt=0)
    action: Literal["warn", "refuse"] = "warn"


class ProcedureConfig(Strict):
    sweep_deg: float = Field(10.0, gt=0, le=45, description="sweep from -sweep_deg to +sweep_deg")
    sweep_steps: int = Field(21, ge=3, le=721)
    tolerance_um: float = Field(10.0, gt=0)
    max_iterations: int = Field(4, ge=1, le=50)
    max_step_mm: float = Field(5.0, gt=0)
    max_center_sigma_um: float = Field(20.0, gt=0)
    calibration_step_mm: float = Field(0.5, gt=0)
    frames_per_step: int = Field(1, ge=1, le=50, description="frames averaged per sweep step")
    systematic_um: float = Field(3.0, ge=0, description=(
        "per-axis systematic standard uncertainty of the offset (bearing error motion, "
        "scale), added to the statistical part"))
    correction_axes: tuple[str, str] = ("x", "y")
    pixel_size_tolerance: float = Field(0.15, gt=0, lt=1,
                                        description="accepted calibration/config disagreement")
    precheck: PrecheckConfig = PrecheckConfig()


class DaemonConfig(Strict):
    socket: str = "/run/alignd/alignd.sock"
    operator_group: str | None = "alignd-operators"
    watchdog: bool = True
    keep_frames: Literal["all", "report", "none"] = Field("all", description=(
        "which camera frames are kept as PNG files: all (the raw data, tens of MB a run), "
        "report (the frame nearest 0 deg of every sweep, which the report draws on) or "
        "none; every frame's hash and features are recorded in the database either way"))


class AligndConfig(Strict):
    version: Literal[1]
    name: str = "alignd"
    controllers: list[ControllerConfig] = Field(..., min_length=1)
    cameras: list[CameraConfig] = Field(..., min_length=1)
    holder: HolderConfig = HolderConfig()
    side_camera: SideCameraConfig = SideCameraConfig()
    procedure: ProcedureConfig = ProcedureConfig()
    daemon: DaemonConfig = DaemonConfig()
    sim: SimConfig | None = None

    @model_validator(mode="after")
    def _consistent(self) -> AligndConfig:
        roles = [a.role for c in self.controllers for a in c.axes]
        dupes = {r for r in roles if roles.count(r) > 1}
        if dupes:
            raise ValueError(f"axis roles used more than once: {sorted(dupes)}")
        for need in ("turntable", *self.procedure.correction_axes):
            if need not in roles:
                raise ValueError(f"no axis with role {need!r} (needed by the procedure)")
        if "top" not in [c.role for c in self.cameras]:
            raise ValueError("no camera with role 'top'")
        names = [c.name for c in self.controllers]
        if len(set(names)) != len(names):
            raise ValueError("controller names must be unique")
        uses_sim = any(c.port == "sim" for c in self.controllers) or any(
            c.source == "sim" for c in self.cameras)
        if uses_sim and self.sim is None:
            raise ValueError("port/source 'sim' needs a 'sim:' section")
        return self

    def axis(self, role: str) -> tuple[ControllerConfig, int]:
        for c in self.controllers:
            for i, a in enumerate(c.axes):
                if a.role == role:
                    return c, i
        raise ConfigError(f"no axis with role {role!r}")

    def camera(self, role: str) -> CameraConfig | None:
        return next((c for c in self.cameras if c.role == role), None)


def frame_keeper(cfg: AligndConfig) -> Callable[[str], bool]:
    """Whether a frame (by its recorder label) is kept as a file, per ``daemon.keep_frames``.

    Sweep frames are labelled ``<kind>-<iteration>-<step>[-<n>]``; "report" keeps, of every
    sweep, the first frame at the step nearest 0 deg (the one the report draws on)."""
    mode = cfg.daemon.keep_frames
    if mode != "report":
        return lambda _label: mode == "all"
    p = cfg.procedure
    angles = [-p.sweep_deg + i * 2 * p.sweep_deg / (p.sweep_steps - 1)
              for i in range(p.sweep_steps)]
    mid = min(range(p.sweep_steps), key=lambda i: abs(angles[i]))

    def keep(label: str) -> bool:
        parts = label.split("-")
        return (len(parts) >= 3 and parts[1].isdigit() and parts[2].isdigit()
                and int(parts[2]) == mid and (len(parts) < 4 or parts[3] == "0"))

    return keep


def _key_path(loc: tuple[object, ...]) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


def parse_config(data: object, source: str = "<config>") -> AligndConfig:
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level")
    try:
        return AligndConfig.model_validate(data)
    except ValidationError as exc:
        lines = [f"{source}: {_key_path(e['loc'])}: {e['msg']}" for e in exc.errors()]
        raise ConfigError("invalid config:\n  " + "\n  ".join(lines)) from None


def load_config(path: str | Path) -> AligndConfig:
    """Load and validate a YAML config file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {exc}") from None
    return parse_config(data, str(p))


def config_hash(cfg: AligndConfig) -> str:
    """SHA-256 of the canonical JSON of the validated config (kept with every run)."""
    return hashlib.sha256(cfg.model_dump_json().encode()).hexdigest()
