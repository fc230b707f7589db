"""Configuration models of the device layer (controllers, axes, cameras, simulated rig).

Pydantic models with unknown keys rejected and units in field names. ``alignd.config``
embeds these in the full instrument config; ``alignd-sim`` reads them alone.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from drivers.stages import resolve as resolve_stage

Role = Literal["turntable", "translator", "x", "y", "z"]


class Strict(BaseModel):
    # allow_inf_nan=False: a limit, tolerance or speed of .inf/.nan is a config error
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SoftLimits(Strict):
    """Soft travel limits in the axis' units (mm or deg). Both are required."""

    min: float
    max: float

    @model_validator(mode="after")
    def _ordered(self) -> SoftLimits:
        if not self.min < self.max:
            raise ValueError(f"min ({self.min}) must be below max ({self.max})")
        return self


class AxisConfig(Strict):
    """One motion axis of a controller, in interface units (mm or deg)."""

    role: Role
    address: int = Field(1, ge=0, le=255, description="SMC100 address / Zaber device / APT channel")
    axis: int = Field(1, ge=1, le=9, description="axis number within a multi-axis device")
    units: Literal["mm", "deg"] = "mm"
    stage: str = Field("", description="stage model, sets the scale, e.g. MTS25-Z8, X-LSM100A")
    soft_limits: SoftLimits
    speed: float = Field(2.0, gt=0, description="units per second")
    accel: float = Field(10.0, gt=0, description="units per second squared")
    deadband: float = Field(0.001, gt=0, description="accepted |read-back - target|")
    retries: int = Field(2, ge=0, le=10)
    approach: Literal["+", "-"] = "+"
    backlash_approach: float = Field(0.05, ge=0, description="pre-position distance")
    stall_timeout_s: float = Field(2.0, gt=0)
    poll_interval_s: float = Field(0.01, gt=0)
    home_timeout_s: float = Field(120.0, gt=0)
    time_scale: float = Field(1.0, gt=0, description="simulated time runs this much faster")


class ControllerConfig(Strict):
    """One controller (one serial port) and the axes it drives."""

    name: str
    protocol: str = Field(..., description=(
        "a registered protocol (drivers.registry): smc100, apt, zaber or a plug-in's"))
    port: str = Field(..., description="pyserial URL or device path; 'sim' = built-in emulator")
    baudrate: int | None = None
    reply_timeout_s: float = Field(0.5, gt=0)
    axes: list[AxisConfig] = Field(..., min_length=1)

    @field_validator("protocol")
    @classmethod
    def _registered(cls, value: str) -> str:
        from drivers import registry  # imports the Axis base class, which imports this module

        known = registry.names()
        if value not in known:
            raise ValueError(f"unknown protocol {value!r}; known: {', '.join(known)}")
        return value

    @model_validator(mode="after")
    def _simulable(self) -> ControllerConfig:
        from drivers import registry

        if self.port == "sim" and not registry.get(self.protocol).simulated:
            raise ValueError(f"protocol {self.protocol!r} has no emulator: use a real port, "
                             "not 'sim'")
        return self

    @model_validator(mode="after")
    def _stages_known_and_limits_inside_travel(self) -> ControllerConfig:
        """Every axis names a stage this protocol knows, in its units, and its soft limits
        lie inside that stage's travel (else the stage drives into its limit switch)."""
        for i, ax in enumerate(self.axes):
            where = f"axes.{i} ({ax.role})"
            try:
                model = resolve_stage(self.protocol, ax.stage, ax.units)
            except ValueError as exc:
                raise ValueError(f"{where}: {exc}") from None
            if model is None:
                continue
            if model.units != ax.units:
                raise ValueError(f"{where}: stage {model.name} moves in {model.units}, the "
                                 f"axis is configured in {ax.units}")
            if model.travel is not None:
                lo, hi = model.travel
                lim = ax.soft_limits
                if not (lo <= lim.min and lim.max <= hi):
                    raise ValueError(
                        f"{where}: soft limits [{lim.min:g}, {lim.max:g}] {ax.units} lie "
                        f"outside the travel of stage {model.name} [{lo:g}, {hi:g}] "
                        f"{ax.units}")
        return self


# a camera's tone curve: a pure power (1 = linear) or a standard's curve by name
NamedCurve = Literal["srgb", "bt709"]
ToneCurve = float | NamedCurve


class LensConfig(Strict):
    """A lens' radial distortion (OpenCV's model, k1 alone), at the streamed frame size.

    From a calibration: ``cv2.calibrateCamera``'s camera matrix (fx, or the mean of fx and
    fy; cx, cy) and its first distortion coefficient (docs/configure.md).
    """

    focal_px: float = Field(..., gt=0, description="focal length in pixels (fx)")
    principal_px: tuple[float, float] = Field(..., description=(
        "principal point [cx, cy] in pixels"))
    k1: float = Field(..., ge=-2.0, le=10.0, description=(
        "radial coefficient in focal-length-normalised coordinates (negative: barrel)"))


class CameraConfig(Strict):
    """A camera source (contract: camera sources in the design notes)."""

    role: Literal["top", "side"]
    source: str = Field(..., description="index, device path, file, folder, URL or 'sim'")
    width: int | None = None
    height: int | None = None
    exposure: float | None = None
    pixel_size_um: float | None = Field(None, gt=0)
    settle_frames: int = Field(1, ge=0, description="frames discarded after a move")
    gamma: Annotated[float, Field(ge=1.0, le=3.0)] | NamedCurve = Field(1.0, description=(
        "the camera's tone curve: a pixel's value is (light)^(1/gamma) of full scale. 1 = "
        "linear (machine-vision cameras as delivered); about 2.2 for webcams and UVC "
        "cameras, which encode sRGB-like; or a standard's curve by name, 'srgb' or "
        "'bt709' (a straight toe, then a power), where the camera's documentation names "
        "it. alignd undoes it before measuring edges: a gamma frame read as linear put "
        "corners 0.3 px off (up to 1.7); BT.709 frames undone as a pure power of 1.9 "
        "0.049 px, by name 0.037 (linear frames 0.037). A simulated camera draws its "
        "frames with it"))
    lens: LensConfig | None = Field(None, description=(
        "the lens' radial distortion (top camera). alignd straightens the holder's sides "
        "with it and measures sweeps in the undistorted image. Unmodelled, a webcam's "
        "barrel distortion shifts the target against the centre of rotation by tens of um "
        "while the run reports 'aligned' (docs/configure.md). Unset: no distortion"))


class FaultConfig(Strict):
    """An injected fault of the simulated rig (see drivers.sim.server).

    A deterministic fault names the command it hits (``on``, with ``nth`` and optionally
    ``following``): "the 3rd reply to a ``TE`` that follows a ``PA``". ``after_commands``
    counts every command, status polls included, so where it lands depends on timing: it
    suits random soak faults, not a test that expects one outcome.
    """

    device: str  # controller name
    kind: Literal["no_reply", "truncated", "garbled", "bad_checksum", "slow_reply", "late_reply",
                  "stall", "limit_switch", "disconnect"]
    on: str | None = Field(None, description=(
        "the command hit, by kind: SMC100 mnemonic ('TE', 'PA'), Zaber command words "
        "('move abs', 'get pos'), APT message id ('0x0453'). A wire fault hits the reply to "
        "it; stall, limit_switch and disconnect fire once it has been received"))
    following: str | None = Field(None, description=(
        "with on: only a command that directly follows one of this kind on the same link"))
    nth: int = Field(1, ge=1, description="with on: the first matching command hit is the nth")
    after_commands: int = Field(0, ge=0, description="let this many commands through first")
    count: int = Field(1, ge=0, description=(
        "how many commands are hit; 0 = all after (with on: every reply from the nth match on)"))
    probability: float = Field(1.0, ge=0, le=1)
    delay_s: float = Field(1.0, ge=0)
    axis: Role | None = None

    @model_validator(mode="after")
    def _one_trigger(self) -> FaultConfig:
        if self.on is not None and self.after_commands:
            raise ValueError("give either on (a command kind) or after_commands, not both")
        if self.on is None and (self.following is not None or self.nth != 1):
            raise ValueError("following and nth need on (the command kind to match)")
        return self


class SimWorldConfig(Strict):
    """The simulated world's geometry and imperfections (all lengths in mm)."""

    axis_px: tuple[float, float] = (652.3, 347.8)
    pixel_size_um: float = 160.0
    top_frame_px: tuple[int, int] = Field((1280, 720), description=(
        "the top camera's frame, width x height (px): the thesis' webcam's 1280 x 720; "
        "another camera's (640 x 480, 1920 x 1080) to try the vision on it"))
    side_frame_px: tuple[int, int] = Field((1280, 720), description=(
        "the side camera's frame, width x height (px)"))
    side_pixel_size_um: float = Field(60.0, gt=0, description=(
        "the side camera's pixel at the sample (um): the pole (6 mm) and the sample (5 mm "
        "thick) 25 mm apart must both stay in its frame"))
    holder_size_mm: tuple[float, float] = (60.0, 40.0)
    rim_radius_mm: float = 150.0  # the thesis turntable; configs/sim.yaml uses a smaller one
    sample_thickness_mm: float = 5.0
    initial_offset_mm: tuple[float, float] | None = None  # None = random from seed
    initial_offset_max_mm: float = 4.0
    yaw_deg: float | None = None  # None = random 1..2 deg
    stage_skew_deg: float = 1.5  # non-squareness of platform x/y
    translator_skew_deg: float = 0.8
    tilt_deg: float = 0.3
    wobble_um: float = 2.0
    stage_repeatability_um: float = 0.5
    backlash_mm: float = 0.004
    turntable_backlash_deg: float = 0.002
    turntable_encoder_error_deg: float = 0.003
    top_camera_zenith_deg: float = 0.5
    top_lens_k1: float = Field(0.0, ge=-1.0, le=10.0, description=(
        "the top camera lens' radial distortion (OpenCV's k1 at the world camera's focal "
        "length, 800 mm / pixel_size_um = 5000 px at 160 um/px, and principal point, "
        "axis_px): what the lens does; cameras[].lens is what the config tells alignd"))
    noise_dn: float = 2.0
    jpeg_quality: int | None = Field(None, ge=10, le=100, description=(
        "both cameras' frames JPEG-coded at this quality (1-100 as libjpeg's), as a UVC "
        "camera streaming MJPEG sends them (the thesis' webcam); null: raw frames"))
    # ---- what differs between rigs (commissioning finds these; see docs/configure.md) ----
    turntable_direction: Literal[1, -1] = Field(1, description=(
        "+1: a positive commanded angle turns the table the way the design notes' R(a) "
        "turns the image; -1: the other way round"))
    turntable_scale: float = Field(1.0, gt=0.5, lt=2.0, description=(
        "true table degrees per commanded degree (a wrong gear ratio or step count)"))
    camera_mirror: bool = Field(False, description="top image mirrored left-right")
    camera_rotation_deg: Literal[0, 90, 180, 270] = Field(0, description=(
        "top camera turned about its optical axis"))
    swap_xy: bool = Field(False, description="the config's x role drives the y stage and back")
    invert_x: bool = Field(False, description="the x role's stage moves the other way")
    invert_y: bool = Field(False, description="the y role's stage moves the other way")
    holder_dn: float | None = Field(None, ge=0, le=255, description=(
        "grey level of the holder's top face (None: the renderer's dark holder)"))

    @model_validator(mode="after")
    def _ranges(self) -> SimWorldConfig:
        if not 0.0 <= self.wobble_um <= 50.0:
            raise ValueError(f"wobble_um {self.wobble_um} outside [0, 50]")
        if self.backlash_mm < 0 or self.turntable_backlash_deg < 0:
            raise ValueError("backlash must not be negative")
        for key, (w, h) in (("top_frame_px", self.top_frame_px),
                            ("side_frame_px", self.side_frame_px)):
            if not (160 <= w <= 8192 and 120 <= h <= 8192):
                raise ValueError(f"{key} {w} x {h} outside 160 x 120 .. 8192 x 8192")
        w, h = self.top_frame_px
        if not (0 <= self.axis_px[0] < w and 0 <= self.axis_px[1] < h):
            raise ValueError(f"axis_px {self.axis_px} outside the {w} x {h} top frame")
        return self


class SimConfig(Strict):
    """The simulated rig: seed, time scale, world and faults."""

    seed: int = 1
    time_scale: float = Field(20.0, gt=0)
    transport: Literal["tcp", "pty", "both"] = "tcp"
    pace_serial: bool = Field(False, description=(
        "emulators take as long as the bytes take at the real baud rate (realistic round "
        "trips; slower)"))
    world: SimWorldConfig = SimWorldConfig()
    faults: list[FaultConfig] = Field(default_factory=list)
    target_log: str | None = Field(None, description=(
        "append every target the emulators receive as a JSON line to this file "
        "(safety tests read it from outside the process)"))
