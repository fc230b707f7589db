"""Simulated cameras: the renderer drawing the simulated world as it is right now."""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Literal

import numpy as np

from drivers.camera import Camera, Frame
from drivers.sim import render
from drivers.sim.world import World


class SimCamera(Camera):
    """A camera looking at the simulated world (top or side view).

    Each grab renders the world's state at that instant, so a frame grabbed after a move
    settled shows the settled pose; one grabbed during a move shows where the stages are.
    """

    def __init__(self, world: World, role: Literal["top", "side"], *,
                 opts: render.RenderOptions | None = None, seed: int = 0,
                 lock: threading.Lock | None = None) -> None:
        super().__init__(f"{role}-camera", f"sim:{role}")
        self.world = world
        self.role = role
        if opts is None:
            opts = render.RenderOptions(read_noise_dn=world.cfg.noise_dn, gradient=(0.08, 0.04))
            if world.cfg.holder_dn is not None:
                opts = dataclasses.replace(opts, holder_dn=world.cfg.holder_dn)
        self.opts = opts
        self.rng = np.random.default_rng(seed)
        self.lock = lock or threading.Lock()
        self._seq = 0
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        t = time.monotonic()
        with self.lock:
            if self.role == "top":
                scene = self.world.top_scene()
                img = render.render_top(scene, self.world.top_camera, self.opts, self.rng)
                meta: dict[str, object] = {"turntable_deg_true": scene.turntable_deg}
            else:
                img = render.render_side(self.world.side_scene(), self.opts, self.rng)
                meta = {}
        self._seq += 1
        meta.update(source=self.source, exposure=1.0, gain=1.0)
        return Frame(img, t, self._seq, meta)
