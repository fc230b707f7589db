"""Build the ``Rig`` a config describes: drivers on their ports, cameras on their sources.

For controllers whose ``port`` is ``sim`` the simulated rig's emulators are started first
and the drivers connect to them over real loopback TCP ports (or ptys), so the simulated
instrument speaks the same bytes as the real one.
"""

from __future__ import annotations

import logging
from typing import Literal

from alignd.config import AligndConfig
from alignd.errors import ConfigError
from alignd.procedures.rig import Rig
from drivers.axis import Axis
from drivers.camera import Camera, open_camera
from drivers.registry import make_axes

log = logging.getLogger(__name__)


def open_rig(cfg: AligndConfig, *, seed: int | None = None,
             transport: Literal["tcp", "pty", "both"] | None = None) -> Rig:
    """Start what is simulated and create (not yet connect) every axis and camera.

    The returned rig's ``close()`` also stops the simulated rig. ``truth`` is set only
    when the whole rig is simulated.
    """
    sim_rig = None
    if cfg.sim is not None and (any(c.port == "sim" for c in cfg.controllers)
                                or any(c.source == "sim" for c in cfg.cameras)):
        from alignd.simulated import open_sim_rig  # only when the config asks for it

        sim_rig = open_sim_rig(cfg, seed=seed, transport=transport)
    try:
        axes: dict[str, Axis] = {}
        for ctl in cfg.controllers:
            time_scale = 1.0
            if ctl.port == "sim":
                assert sim_rig is not None and cfg.sim is not None
                ctl = ctl.model_copy(update={"port": sim_rig.url(ctl.name)})
                time_scale = cfg.sim.time_scale
            for ax in make_axes(ctl, time_scale=time_scale):
                axes[ax.config.role] = ax
        cameras: dict[str, Camera] = {}
        for cam in cfg.cameras:
            if cam.source == "sim":
                assert sim_rig is not None
                cameras[cam.role] = sim_rig.camera(cam.role)
            else:
                cameras[cam.role] = open_camera(cam.role, cam.source, width=cam.width,
                                                height=cam.height, exposure=cam.exposure,
                                                settle_frames=cam.settle_frames)
    except Exception:
        if sim_rig is not None:
            sim_rig.stop()
        raise
    whole_sim = sim_rig is not None and all(c.port == "sim" for c in cfg.controllers)
    rig = Rig(axes=axes, cameras=cameras, name=cfg.name,
              truth=sim_rig.truth if whole_sim and sim_rig is not None else None)
    if sim_rig is not None:
        rig.on_close.append(sim_rig.stop)
    if "turntable" not in axes:
        rig.close()
        raise ConfigError("config has no turntable axis")
    return rig
