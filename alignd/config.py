"""The instrument config: one YAML file, pydantic models, unknown keys rejected.

A bad config fails at load with the file, the key path and the reason (``ConfigError``).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from alignd.errors import ConfigError
from drivers.config import CameraConfig, ControllerConfig, SimConfig


class Strict(BaseModel):
    # allow_inf_nan=False: a tolerance or size of .inf/.nan is a config error, not a value
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


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

    pole_roi_px: tuple[int, int, int, int] | None = Field(None, description=(
        "the region holding the vertical reference pole, [x0, y0, x1, y1] px; unset = found "
        "automatically"))
    sample_roi_px: tuple[int, int, int, int] | None = Field(None, description=(
        "the region holding the sample's edge, [x0, y0, x1, y1] px; unset = the nearest "
        "long straight edge beside the pole"))

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
    tilt_frames: int = Field(8, ge=1, le=100, description=(
        "side-camera frames the tilt is averaged over; the run reports the mean and its "
        "standard uncertainty (one frame's fit is good to 0.0005-0.006 deg)"))
    tilt_u_target_deg: float | None = Field(0.0006, gt=0, description=(
        "while the tilt's standard uncertainty is above this (deg), take as many side frames "
        "again, up to tilt_max_frames (on MJPEG frames it falls slowly: the coding of a still "
        "view is an error the frames share, which more frames do not average). null: "
        "tilt_frames frames, no more"))
    tilt_max_frames: int = Field(64, ge=1, le=1000, description=(
        "the most side frames the tilt pre-check takes when tilt_u_target_deg asks for more "
        "(never fewer than tilt_frames); about 0.1 s a frame"))
    rim_frames: int = Field(8, ge=1, le=100, description=(
        "top-camera frames averaged for the rim's eccentricity; the run reports e and its "
        "standard uncertainty (at e ~ 0.01-0.03 one frame's e is uncertain to 0.001-0.005)"))
    rim_turn_deg: float = Field(0.0, ge=0, le=45, description=(
        "turntable step (deg) between the rim frames: 0 takes them all where the turntable "
        "stands; > 0 turns the disc between frames (centred on where it stands, inside the "
        "soft limits; it goes back afterwards), so a textured disc's pattern, which no "
        "number of still frames averages, moves and averages out: 180 / rim_frames (22.5 "
        "for 8 frames) cancels its second harmonic, what moves e (docs/vision.md, Rim)"))
    action: Literal["warn", "refuse"] = "warn"


class ContinuousConfig(Strict):
    """The continuous (on-the-fly) sweep: the turntable turns while the top camera streams.

    Each frame's angle comes from the images (rigid fit), the turntable's read-back at the
    frame's time serving as the prior; the speed is checked against the motion blur."""

    speed_deg_s: float = Field(5.0, gt=0, le=90, description=(
        "turntable speed during the sweep (deg/s); more frames per step (when a run must "
        "measure better) divide it"))
    frame_rate_hz: float = Field(30.0, gt=0, le=1000, description=(
        "frames per second the top camera streams during the sweep"))
    exposure_s: float = Field(0.005, gt=0, le=1, description=(
        "the top camera's exposure time (s) while streaming; set the camera to it (the "
        "simulated camera uses it)"))
    max_blur_px: float = Field(0.5, gt=0, le=20, description=(
        "the most motion blur at the holder's corners a frame may have (px): speed (rad/s) "
        "x exposure_s x corner radius / pixel size"))
    corner_radius_mm: float | None = Field(None, gt=0, description=(
        "distance of the holder's farthest corner from the axis (mm) for the blur limit; "
        "null: half the holder's diagonal plus procedure.max_step_mm"))
    on_blur: Literal["refuse", "cap"] = Field("refuse", description=(
        "refuse: a speed whose blur exceeds max_blur_px is a config error; cap: turn "
        "slower, at the fastest speed within the limit"))

    @model_validator(mode="after")
    def _exposure(self) -> ContinuousConfig:
        if self.exposure_s >= 1.0 / self.frame_rate_hz:
            raise ValueError(f"exposure_s {self.exposure_s:g} s does not fit in a frame period "
                             f"at frame_rate_hz {self.frame_rate_hz:g} "
                             f"({1.0 / self.frame_rate_hz:g} s): lower one of them")
        return self


class ProcedureConfig(Strict):
    sweep_deg: float = Field(10.0, gt=0, le=45, description="sweep from -sweep_deg to +sweep_deg")
    sweep_steps: int = Field(21, ge=3, le=721)
    tolerance_um: float = Field(10.0, gt=0)
    max_iterations: int = Field(4, ge=1, le=50, description=(
        "the most correction moves one alignment makes"))
    max_sweeps: int = Field(8, ge=1, le=50, description=(
        "the most measurement sweeps one run makes (align or check)"))
    max_step_mm: float = Field(5.0, gt=0)
    max_center_sigma_um: float = Field(20.0, gt=0)
    calibration_step_mm: float = Field(0.5, gt=0)
    frames_per_step: int = Field(1, ge=1, le=50, description="frames averaged per sweep step")
    max_frames_per_step: int = Field(4, ge=1, le=50, description=(
        "the most frames per step a run averages when it must measure better to decide"))
    max_sweep_deg: float | None = Field(45.0, gt=0, le=180, description=(
        "the widest sweep (half-width, deg): that of a sweep that is to decide under "
        "guarded acceptance, and the most a run widens to when it must measure better; "
        "kept inside the turntable's soft limits; null: sweep_deg only"))
    verdict_sweep_steps: int | None = Field(11, ge=3, le=721, description=(
        "steps of a sweep that is to decide under guarded acceptance (a check's, and every "
        "one after a correction move), which turns over max_sweep_deg: fewer, larger steps "
        "over a wider angle give a better centre in the same time; null: sweep_steps"))
    verdict_frames_per_step: int = Field(2, ge=1, le=50, description=(
        "frames averaged per step in a sweep that is to decide (as verdict_sweep_steps): a "
        "frame costs a frame period, a step a turntable move; at least frames_per_step, at "
        "most max_frames_per_step"))
    alternate_sweeps: bool = Field(True, description=(
        "start each sweep at whichever end is nearer the turntable (every step of a sweep "
        "approached from one side, so the backlash stays out; only a constant angle offset "
        "of the backlash differs, which does not move the centre); false: always in the "
        "axis' approach direction (a return to the start before each sweep)"))
    predict_after_small_move: bool = Field(True, description=(
        "end an alignment without a sweep after its last correction move when that move "
        "was small (the calibration's scale error on it below half stage_repeatability_um) "
        "and the offset predicted after it, with the stages' landing scatter added to the "
        "budget, is within under the decision rule with U at most target_u_fraction of the "
        "tolerance; false: a verification sweep after every move"))
    systematic_um: float = Field(3.0, ge=0, description=(
        "per-axis error-motion floor assumed when no runout map is available (with a map "
        "the floor is the map's uncertainty plus the scatter between repeated sweeps)"))
    stage_repeatability_um: float = Field(1.0, ge=0, description=(
        "1-sigma per-axis landing scatter of the correction stages: no move is made when "
        "it would gain less than this"))
    target_u_fraction: float = Field(0.5, gt=0, le=1, description=(
        "an alignment measures better (within max_sweep_deg, max_frames_per_step and "
        "max_sweeps) before its verdict until U is at most this fraction of the tolerance"))
    decision_rule: Literal["guarded", "simple"] = Field("guarded", description=(
        "guarded: guarded acceptance per ISO 14253-1 (within when offset <= tolerance - U); "
        "simple: simple acceptance (within when offset <= tolerance)"))
    correction_axes: tuple[str, str] = ("x", "y")
    turntable_direction: Literal[1, -1] = Field(1, description=(
        "+1: a positive turntable angle turns the top image as R(a) of the design notes "
        "(counter-clockwise on screen, y down); -1: the other way round. A valid commission "
        "record's measured direction takes precedence"))
    pixel_size_tolerance: float = Field(0.15, gt=0, lt=1,
                                        description="accepted calibration/config disagreement")
    precheck: PrecheckConfig = PrecheckConfig()
    sweep_mode: Literal["step", "continuous"] = Field("step", description=(
        "step: move, settle and grab at each of sweep_steps angles (the default); "
        "continuous: turn at procedure.continuous.speed_deg_s while the top camera "
        "streams, each frame's angle from the images"))
    continuous: ContinuousConfig = Field(ContinuousConfig(), description=(
        "settings of the continuous sweep (sweep_mode: continuous)"))

    @field_validator("correction_axes")
    @classmethod
    def _two_different(cls, axes: tuple[str, str]) -> tuple[str, str]:
        if axes[0] == axes[1]:
            raise ValueError(f"names {axes[0]!r} twice; the correction needs two different "
                             "linear axes, e.g. [x, y]")
        return axes

    @model_validator(mode="after")
    def _sweeps(self) -> ProcedureConfig:
        if self.max_sweep_deg is not None and self.max_sweep_deg < self.sweep_deg:
            raise ValueError(f"max_sweep_deg {self.max_sweep_deg:g} is narrower than sweep_deg "
                             f"{self.sweep_deg:g}")
        if self.max_frames_per_step < self.frames_per_step:
            raise ValueError(f"max_frames_per_step {self.max_frames_per_step} is below "
                             f"frames_per_step {self.frames_per_step}")
        return self


class CommissionConfig(Strict):
    """How ``alignctl commission`` measures the rig (once per rig and after a rebuild)."""

    sweep_deg: float = Field(360.0, ge=30, le=360, description=(
        "total turntable span of the runout sweep, centred on 0 (a full turn where the "
        "cables allow; clipped to the turntable's soft limits)"))
    step_deg: float = Field(5.0, ge=0.5, le=30, description="angle step of that sweep")
    stage_step_mm: float = Field(0.5, gt=0, le=5, description=(
        "length of the there-and-back moves of each translation axis"))
    repeats: int = Field(3, ge=2, le=10, description=(
        "there-and-back moves per axis (backlash and repeatability)"))
    pixel_size_warn: float = Field(0.05, gt=0, lt=1, description=(
        "relative disagreement of the measured and configured pixel size that warns"))
    pixel_size_fail: float = Field(0.10, gt=0, lt=1, description="... and that fails")
    holder_size_warn: float = Field(0.015, gt=0, lt=1, description=(
        "relative disagreement of the measured and configured holder size that warns"))
    holder_size_fail: float = Field(0.04, gt=0, lt=1, description="... and that fails")
    rim_radius_mm: float | None = Field(None, gt=0, description=(
        "outer radius of the turntable's rim (for the top camera's zenith angle)"))
    top_camera_height_mm: float | None = Field(None, gt=0, description=(
        "height of the top camera's lens above the turntable (for the zenith angle)"))


class DaemonConfig(Strict):
    socket: str = "/run/alignd/alignd.sock"
    operator_group: str | None = "alignd-operators"
    watchdog: bool = True
    keep_frames: Literal["all", "report", "none"] = Field("all", description=(
        "which camera frames are kept as PNG files: all (the raw data, tens of MB a run), "
        "report (the frame nearest 0 deg of every sweep and the side pre-check's first, "
        "which the report draws on) or "
        "none; every frame's hash and features are recorded in the database either way"))
    web: str | None = Field(None, description=(
        "HOST:PORT of the read-only web dashboard and /metrics (off unless set; a bare "
        "':8080' binds 127.0.0.1); alignd --web overrides it"))


class AligndConfig(Strict):
    version: Literal[1]
    name: str = "alignd"
    controllers: list[ControllerConfig] = Field(..., min_length=1)
    cameras: list[CameraConfig] = Field(..., min_length=1)
    holder: HolderConfig = HolderConfig()
    side_camera: SideCameraConfig = Field(default_factory=SideCameraConfig, description=(
        "where the side camera sees the pole and the sample (tilt pre-check)"))
    procedure: ProcedureConfig = ProcedureConfig()
    commission: CommissionConfig = CommissionConfig()
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
        if self.procedure.sweep_mode == "continuous":
            try:
                continuous_speed(self)
            except ConfigError as exc:
                raise ValueError(str(exc)) from None
        return self

    def axis(self, role: str) -> tuple[ControllerConfig, int]:
        for c in self.controllers:
            for i, a in enumerate(c.axes):
                if a.role == role:
                    return c, i
        raise ConfigError(f"no axis with role {role!r}")

    def camera(self, role: str) -> CameraConfig | None:
        return next((c for c in self.cameras if c.role == role), None)


def continuous_speed(cfg: AligndConfig, frames_per_step: int = 1) -> tuple[float, float]:
    """The turntable speed (deg/s) of a continuous sweep and the motion blur (px) it gives at
    the holder's corners: speed (rad/s) x ``exposure_s`` x the corners' radius from the axis
    / the top camera's pixel size. ``frames_per_step`` > 1 (a run measuring better) turns
    that many times slower.

    Raises ``ConfigError`` naming the keys when the blur exceeds ``max_blur_px`` (unless
    ``on_blur: cap``, which slows down to the limit), when no pixel size is known, or when
    the speed is above the turntable's configured speed."""
    c = cfg.procedure.continuous
    key = "procedure.continuous"
    cam = cfg.camera("top")
    px_um = cam.pixel_size_um if cam is not None else None
    if px_um is None and cfg.sim is not None:
        px_um = cfg.sim.world.pixel_size_um
    if px_um is None:
        raise ConfigError("procedure.sweep_mode continuous needs cameras.top.pixel_size_um "
                          "to check the motion blur (alignctl commission measures it)")
    radius = c.corner_radius_mm
    if radius is None:
        radius = math.hypot(*cfg.holder.size_mm) / 2 + cfg.procedure.max_step_mm
    px_per_rad_s = c.exposure_s * radius * 1000.0 / px_um  # blur (px) per rad/s
    speed = c.speed_deg_s / max(frames_per_step, 1)
    blur = math.radians(speed) * px_per_rad_s
    if blur > c.max_blur_px:
        v_max = math.degrees(c.max_blur_px / px_per_rad_s)
        if c.on_blur == "refuse":
            raise ConfigError(
                f"{key}.speed_deg_s {speed:g} deg/s x {key}.exposure_s {c.exposure_s:g} s x "
                f"corner radius {radius:.1f} mm ({key}.corner_radius_mm) / "
                f"cameras.top.pixel_size_um {px_um:g} um = {blur:.2f} px of motion blur at "
                f"the holder's corners, above {key}.max_blur_px {c.max_blur_px:g}: lower "
                f"speed_deg_s to {v_max:.3g} deg/s or less, shorten exposure_s, or set "
                f"{key}.on_blur: cap")
        speed, blur = v_max, c.max_blur_px
    _, i = cfg.axis("turntable")
    top = cfg.axis("turntable")[0].axes[i].speed
    if speed > top:
        raise ConfigError(f"{key}.speed_deg_s {speed:g} deg/s is above the turntable's "
                          f"configured speed {top:g} deg/s (controllers: axes: speed)")
    return speed, blur


# the labels of the pre-check's frames in a run's record (``<prefix>NNN``), and the side
# pre-check's first frame, which the report draws
RIM_FRAME_PREFIX, SIDE_FRAME_PREFIX = "precheck-rim-", "precheck-side-"
SIDE_FIRST_LABEL = f"{SIDE_FRAME_PREFIX}000"


def frame_keeper(cfg: AligndConfig) -> Callable[[str], bool]:
    """Whether a frame (by its recorder label) is kept as a file, per ``daemon.keep_frames``.

    Sweep frames are labelled ``<kind>-<iteration>-<step>[-<n>]``; "report" keeps, of every
    sweep, the first frame at the step nearest 0 deg, and the side pre-check's first frame
    (``precheck-side-000``): the ones the report draws on."""
    mode = cfg.daemon.keep_frames
    if mode != "report":
        return lambda _label: mode == "all"
    p = cfg.procedure
    angles = [-p.sweep_deg + i * 2 * p.sweep_deg / (p.sweep_steps - 1)
              for i in range(p.sweep_steps)]
    mid = min(range(p.sweep_steps), key=lambda i: abs(angles[i]))
    if p.sweep_mode == "continuous":  # streamed frames: the one passing 0 deg
        mid = round(p.sweep_deg / p.continuous.speed_deg_s * p.continuous.frame_rate_hz)

    def keep(label: str) -> bool:
        if label == SIDE_FIRST_LABEL:
            return True
        parts = label.split("-")
        return (len(parts) >= 3 and parts[1].isdigit() and parts[2].isdigit()
                and int(parts[2]) == mid and (len(parts) < 4 or parts[3] == "0"))

    return keep


RECORDS_MARGIN_BYTES = 4 * 1024 * 1024  # a run's database records (sweeps, events, result)
DEFAULT_FRAME_PX = (1280, 720)  # a camera whose config gives no size


def run_footprint(cfg: AligndConfig) -> tuple[int, str]:
    """Disk space one run may need at most, and how that was reckoned (for messages).

    The frames dominate: an ``align`` may measure up to ``max_iterations`` times with a
    verification sweep after each, every sweep ``sweep_steps x frames_per_step`` frames
    (a continuous sweep: every streamed frame over the widest sweep), plus the
    calibration (2 stages x 4 positions, refreshed up to ``MAX_CAL_REFRESHES`` times),
    and the pre-check's rim frames and side frames (as many as it may take).
    A frame file is a PNG, at most about its raw size: width x height, x3 for a real
    camera that may deliver colour. ``daemon.keep_frames`` says which are files."""
    from alignd.procedures.align import MAX_CAL_REFRESHES

    p = cfg.procedure
    sweeps = 2 * p.max_iterations
    per_sweep = p.sweep_steps * p.frames_per_step
    if p.sweep_mode == "continuous":  # every streamed frame, over the widest sweep
        c = p.continuous
        per_sweep = math.ceil((2 * max(p.max_sweep_deg or p.sweep_deg, p.sweep_deg) + 2)
                              * p.frames_per_step / c.speed_deg_s * c.frame_rate_hz)
    pc = p.precheck
    side = cfg.camera("side")
    side_frames = 0
    if cfg.daemon.keep_frames == "all":
        # the sweeps, the calibration and the pre-check's rim frames; the side camera's
        # pre-check frames apart (up to tilt_max_frames while u is above its target)
        frames = sweeps * per_sweep + \
            (1 + MAX_CAL_REFRESHES) * 2 * 4 * p.frames_per_step + pc.rim_frames
        if side is not None:
            side_frames = max(pc.tilt_frames, pc.tilt_max_frames if pc.tilt_u_target_deg
                              else 0)
    elif cfg.daemon.keep_frames == "report":
        frames = sweeps
        side_frames = 1 if side is not None else 0
    else:
        frames = 0

    def size(cam: CameraConfig | None) -> tuple[int, int, int]:
        w, h = (cam.width, cam.height) if cam and cam.width and cam.height else DEFAULT_FRAME_PX
        return w, h, 1 if cam is not None and cam.source == "sim" else 3

    top_wh, side_wh = size(cfg.camera("top")), size(side)
    total = (frames * math.prod(top_wh) + side_frames * math.prod(side_wh)
             + RECORDS_MARGIN_BYTES)
    how = f"{frames} {'top ' if side_frames else ''}frames of {'x'.join(map(str, top_wh))} bytes"
    if side_frames:
        how += (f" and {side_frames} side frame{'s' if side_frames > 1 else ''} of "
                f"{'x'.join(map(str, side_wh))} bytes")
    how += (f" (keep_frames {cfg.daemon.keep_frames}) "
            f"+ {RECORDS_MARGIN_BYTES / 2**20:.0f} MiB of records")
    return total, how


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


def check_config_file(path: str | Path) -> tuple[AligndConfig, list[str]]:
    """Validate a config without touching hardware: the model's checks (``ConfigError``)
    plus what can only be judged together, returned as warnings."""
    cfg = load_config(path)
    notes: list[str] = []
    tc, i = cfg.axis("turntable")
    lim = tc.axes[i].soft_limits
    p = cfg.procedure
    if not (lim.min <= -p.sweep_deg and p.sweep_deg <= lim.max):
        raise ConfigError(f"{path}: procedure.sweep_deg {p.sweep_deg:g} exceeds the "
                          f"turntable soft limits [{lim.min:g}, {lim.max:g}]")
    half = cfg.commission.sweep_deg / 2
    if -half < lim.min or half > lim.max:
        notes.append(f"commission.sweep_deg {cfg.commission.sweep_deg:g} will be clipped to "
                     f"the turntable soft limits [{lim.min:g}, {lim.max:g}]")
    for c in cfg.controllers:
        if c.port.startswith("/dev/") and not Path(c.port).exists():
            notes.append(f"controllers.{c.name}.port {c.port} does not exist now (device "
                         "unplugged, or a udev rule missing?)")
    for cam in cfg.cameras:
        if cam.source.startswith("/dev/") and not Path(cam.source).exists():
            notes.append(f"cameras.{cam.role}.source {cam.source} does not exist now")
        if cam.role == "top" and cam.pixel_size_um is None:
            notes.append("cameras.top.pixel_size_um is not set: calibration cannot check "
                         "the image scale (alignctl commission measures it)")
    tu, tv = cfg.holder.target_mm
    su, sv = cfg.holder.size_mm
    if abs(tu) <= su / 2 and abs(tv) <= sv / 2:
        notes.append(f"holder.target_mm {cfg.holder.target_mm} lies inside the holder "
                     f"({su:g} x {sv:g} mm): the target is the middle of the sample's "
                     "surface, outside the holder's top face")
    return cfg, notes
