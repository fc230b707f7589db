"""Simulated cameras: the renderer drawing the simulated world over each frame's exposure."""

from __future__ import annotations

import dataclasses
import math
import threading
from typing import Literal

import numpy as np

from drivers.camera import Camera, Frame
from drivers.clock import SYSTEM_CLOCK, Clock
from drivers.config import SimWorldConfig, ToneCurve
from drivers.sim import render
from drivers.sim.clock import ScaledClock
from drivers.sim.world import World
from drivers.tone_curves import is_linear

BLUR_STEP_PX = 0.25  # sub-exposures are rendered this far apart along the fastest corner
MAX_SUBFRAMES = 24


def framed(opts: render.RenderOptions, cfg: SimWorldConfig,
           role: Literal["top", "side"]) -> render.RenderOptions:
    """``opts`` with the world's frame size for camera ``role`` (and, for the side camera,
    its pixel size): what the camera draws and where the world's truth puts it in px."""
    if role == "top":
        return dataclasses.replace(opts, size_px=cfg.top_frame_px)
    return dataclasses.replace(opts, size_px=cfg.side_frame_px,
                               side_pixel_size_um=cfg.side_pixel_size_um)


class SimCamera(Camera):
    """A camera looking at the simulated world (top or side view).

    A grab ends an exposure of ``exposure_s`` seconds at that instant: a frame grabbed
    after a move settled shows the settled pose; one grabbed during a move shows the
    stages where they were over the exposure, smeared as a real sensor smears them (the
    top view is rendered at sub-exposure instants along the way and averaged, as many as
    keep the fastest corner's steps under ``BLUR_STEP_PX``). The frame's timestamp is the
    middle of the exposure, on ``clock`` (the rig's: a manual clock for the direct rig,
    the machine's monotonic clock otherwise). ``gamma``: the camera's tone curve
    (:attr:`drivers.sim.render.RenderOptions.gamma`), as a camera config's ``gamma`` says.
    ``sim.world.jpeg_quality`` codes every frame as a camera streaming MJPEG does.
    """

    def __init__(self, world: World, role: Literal["top", "side"], *,
                 opts: render.RenderOptions | None = None, seed: int = 0,
                 lock: threading.Lock | None = None, clock: Clock | None = None,
                 exposure_s: float = 0.0, gamma: ToneCurve = 1.0) -> None:
        super().__init__(f"{role}-camera", f"sim:{role}")
        self.world = world
        self.role = role
        if opts is None:
            opts = render.RenderOptions(read_noise_dn=world.cfg.noise_dn, gradient=(0.08, 0.04))
            if world.cfg.holder_dn is not None:
                opts = dataclasses.replace(opts, holder_dn=world.cfg.holder_dn)
            if role == "top" and world.cfg.top_lens_k1:
                opts = dataclasses.replace(opts, k1=world.cfg.top_lens_k1)
        # the frame is the world's, given options or not (its top camera projects into it)
        opts = framed(opts, world.cfg, role)
        # the camera's tone curve (the camera config's gamma) over the options' own
        self.opts = opts if is_linear(gamma) else dataclasses.replace(opts, gamma=gamma)
        self.rng = np.random.default_rng(seed)
        self.lock = lock or threading.Lock()
        self.clock = clock or SYSTEM_CLOCK
        if not (math.isfinite(exposure_s) and exposure_s >= 0):
            raise ValueError(f"exposure_s must be >= 0 s, got {exposure_s!r}")
        self.exposure_s = exposure_s
        self._seq = 0
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def _world_exposure(self) -> tuple[float, float]:
        """Start and end of the exposure on the world's clock (a scaled clock runs the
        world ``scale`` times faster than the camera's seconds)."""
        ax = next(iter(self.world.axes.values()), None)
        scale = ax.clock.scale if ax is not None and isinstance(ax.clock, ScaledClock) else 1.0
        end = self.world.now()
        return end - self.exposure_s * scale, end

    def _render_top(self) -> tuple[np.ndarray, float]:
        """The top frame integrated over the exposure, and the true angle at its middle."""
        t0, t1 = self._world_exposure()
        cam = self.world.top_camera
        if t1 <= t0:
            scene = self.world.top_scene()
            return render.render_top(scene, cam, self.opts, self.rng), scene.turntable_deg
        a = cam.project(self.world.top_scene(t0).holder_corners_mm)
        b = cam.project(self.world.top_scene(t1).holder_corners_mm)
        travel = float(np.max(np.hypot(*(b - a).T)))
        n = min(max(math.ceil(travel / BLUR_STEP_PX), 1), MAX_SUBFRAMES)
        mid = self.world.turntable_deg((t0 + t1) / 2)
        if n == 1:
            scene = self.world.top_scene((t0 + t1) / 2)
            return render.render_top(scene, cam, self.opts, self.rng), mid
        clean = dataclasses.replace(self.opts, read_noise_dn=0.0, electrons_per_dn=0.0,
                                    quantize=False)
        acc: np.ndarray | None = None
        for k in range(n):
            sub = render.render_top(self.world.top_scene(t0 + (k + 0.5) / n * (t1 - t0)),
                                    cam, clean, None)
            acc = sub if acc is None else acc + sub
        assert acc is not None
        # the sensor's noise and quantisation once, on the integrated light
        sensor = dataclasses.replace(self.opts, gradient=(0.0, 0.0), shadow=None,
                                     blur_sigma_px=0.0)
        return render.finish(acc / np.float32(n), sensor, self.rng), mid

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        with self.lock:
            if after is not None:  # the exposure starts after ``after`` (a settled stage)
                wait = after + self.exposure_s - self.clock.now()
                if wait > 0:
                    self.clock.sleep(wait)
            t = self.clock.now() - self.exposure_s / 2
            if self.role == "top":
                img, angle = self._render_top()
                meta: dict[str, object] = {"turntable_deg_true": angle}
            else:
                img = render.render_side(self.world.side_scene(), self.opts, self.rng)
                meta = {}
        q = self.world.cfg.jpeg_quality
        if q is not None and img.dtype == np.uint8:
            img = render.mjpeg(img, q)
        self._seq += 1
        meta.update(source=self.source, exposure=1.0, gain=1.0, exposure_s=self.exposure_s)
        return Frame(img, t, self._seq, meta)
