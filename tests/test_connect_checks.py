"""At connect, what the controllers report is compared with the config (issue 9).

Each case serves an emulator on a loopback TCP port and connects the real driver through a
``Rig``: the controller's own limits (SMC100 ``SL?``/``SR?``, Zaber ``limit.min``/
``limit.max``) must contain the configured soft limits, and a reported stage that changes
units or travel refuses to run; a lesser identity mismatch is a warning naming both.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import numpy as np
import pytest

from alignd.procedures.rig import Rig
from drivers import newport_smc100, thorlabs_apt, zaber_ascii
from drivers.axis import Axis
from drivers.config import ControllerConfig
from drivers.errors import ConfigMismatchError
from drivers.sim import apt_emu, smc100_emu, zaber_emu
from drivers.sim.clock import ManualClock
from drivers.sim.emulator import Emulator
from drivers.sim.kinematics import SimAxis
from drivers.sim.server import EmulatorServer

TURNTABLE = {"role": "turntable", "address": 1, "units": "deg", "stage": "URS75BCC",
             "soft_limits": {"min": -30.0, "max": 30.0}, "speed": 20.0, "accel": 80.0}
TRANSLATOR = {"role": "translator", "address": 1, "units": "mm", "stage": "MTS25-Z8",
              "soft_limits": {"min": 0.5, "max": 24.5}, "speed": 2.0, "accel": 4.0}
PLATFORM_X = {"role": "x", "address": 1, "units": "mm", "stage": "X-LSM050A",
              "soft_limits": {"min": 2.0, "max": 48.0}, "speed": 5.0, "accel": 20.0}


@contextlib.contextmanager
def connected(protocol: str, axis: dict[str, object], emulator: Emulator
              ) -> Iterator[Rig]:
    """The emulator on a TCP port, the real driver connected to it through a Rig."""
    with EmulatorServer(emulator, "tcp") as srv:
        ctl = ControllerConfig(name=emulator.name, protocol=protocol,  # type: ignore[arg-type]
                               port=srv.url, axes=[axis])  # type: ignore[list-item]
        module = {"smc100": newport_smc100, "apt": thorlabs_apt, "zaber": zaber_ascii}[protocol]
        axes: list[Axis] = list(module.make_axes(ctl))
        rig = Rig(axes={a.config.role: a for a in axes}, cameras={})
        try:
            rig.connect()
            yield rig
        finally:
            rig.close()


def sim_axis(protocol: str, axis: dict[str, object], clock: ManualClock) -> SimAxis:
    ctl = ControllerConfig(name="c", protocol=protocol, port="sim",  # type: ignore[arg-type]
                           axes=[axis])  # type: ignore[list-item]
    module = {"smc100": smc100_emu, "apt": apt_emu, "zaber": zaber_emu}[protocol]
    phys = module.physics_for(ctl.axes[0])
    return SimAxis(str(axis["role"]), phys, clock, np.random.default_rng(0),
                   start=(phys.travel_min + phys.travel_max) / 2 if axis["units"] == "mm"
                   else 0.0)


def smc100(stage: str = "URS75BCC") -> smc100_emu.Smc100Emulator:
    clock = ManualClock()
    return smc100_emu.Smc100Emulator("turntable", {1: sim_axis("smc100", TURNTABLE, clock)},
                                     clock, stage=stage)


def test_matching_controllers_connect_without_warnings(
        caplog: pytest.LogCaptureFixture) -> None:
    clock = ManualClock()
    with connected("smc100", TURNTABLE, smc100()) as rig:
        assert rig.warnings == []
    emu = apt_emu.AptEmulator("translator", {1: sim_axis("apt", TRANSLATOR, clock)}, clock)
    with connected("apt", TRANSLATOR, emu) as rig:
        assert rig.warnings == []
    emu = zaber_emu.ZaberEmulator("platform", {1: sim_axis("zaber", PLATFORM_X, clock)}, clock)
    with connected("zaber", PLATFORM_X, emu) as rig:
        assert rig.warnings == [] and rig.identities["x"].stage == "X-LSM050A"


def test_smc100_software_limits_narrower_than_the_config_refuse_to_run() -> None:
    emu = smc100()
    emu.ctl[1].sr = 20.0  # the controller's stored SR: 20 deg, the config asks for 30
    with pytest.raises(ConfigMismatchError) as err, connected("smc100", TURNTABLE, emu):
        pass
    msg = str(err.value)
    assert "soft limits [-30, 30] deg" in msg and "controller reports [-170, 20]" in msg
    assert "device turntable" in msg


def test_smc100_other_stage_of_the_same_kind_is_a_warning_naming_both(
        caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING), connected("smc100", TURNTABLE,
                                                     smc100("URS100BCC")) as rig:
        assert len(rig.warnings) == 1
    assert "'URS100BCC' where the config says 'URS75BCC'" in rig.warnings[0]
    assert rig.warnings[0] in caplog.text


def test_zaber_limit_max_below_the_config_refuses_to_run() -> None:
    clock = ManualClock()
    emu = zaber_emu.ZaberEmulator("platform", {1: sim_axis("zaber", PLATFORM_X, clock)}, clock)
    steps_40mm = round(40.0 / zaber_emu.XLSM_MICROSTEP_MM)
    assert emu.handle(f"/1 1 set limit.max {steps_40mm}\n".encode()) == \
        b"@01 1 OK IDLE WR 0\r\n"
    with pytest.raises(ConfigMismatchError, match=r"\[2, 48\] mm .* reports \[0, 40\] mm"), \
            connected("zaber", PLATFORM_X, emu):
        pass


def test_zaber_device_of_another_travel_refuses_to_run() -> None:
    clock = ManualClock()
    emu = zaber_emu.ZaberEmulator("platform", {1: sim_axis("zaber", PLATFORM_X, clock)}, clock,
                                  models={1: "X-LSM100A"})
    with pytest.raises(ConfigMismatchError) as err, connected("zaber", PLATFORM_X, emu):
        pass
    assert "reports stage X-LSM100A (mm, travel 0..101.6)" in str(err.value)
    assert "config says X-LSM050A (mm, travel 0..50.8)" in str(err.value)


def test_apt_stage_id_of_another_travel_refuses_and_empty_serial_warns() -> None:
    clock = ManualClock()
    emu = apt_emu.AptEmulator("translator", {1: sim_axis("apt", TRANSLATOR, clock)}, clock,
                              stage="MTS50-Z8")
    with pytest.raises(ConfigMismatchError, match=r"reports stage MTS50-Z8 .* config says "
                       r"MTS25-Z8"), connected("apt", TRANSLATOR, emu):
        pass
    emu = apt_emu.AptEmulator("translator", {1: sim_axis("apt", TRANSLATOR, clock)}, clock)
    emu.ident.serial = 0
    with connected("apt", TRANSLATOR, emu) as rig:
        assert rig.warnings == ["translator: Thorlabs KDC101 reports no serial number "
                                "(got '0'); runs cannot name the unit"]
