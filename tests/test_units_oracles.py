"""Every unit conversion of the three protocols, checked against a second source (issue 9).

Second sources, written out here rather than imported from our code:
- Zaber: the A-/X-series command reference ("Set Target Speed": data = microsteps/s x
  1.6384; "Set Acceleration": actual = 10000 x data / 1.6384 microsteps/s^2, max 32767) and
  the X-LSM microstep 0.047625 um; ``zaber-motion`` (Zaber's own client, native library,
  offline with ``identify_devices=False``) reads what our driver left in the emulator.
- Thorlabs: the APT protocol document's scaling table (section "position, velocity and
  acceleration units": MTS25/50-Z8 34304 counts/mm, 767367.49 per mm/s, 261.93 per mm/s^2;
  PRM1-Z8 1919.64 /deg, 42941.66, 14.66; K10CR1 136533 /deg, 7329109, 1502) and
  ``pylablib``'s Kinesis driver, which detects the stage from the emulator's HW_GET_INFO and
  converts with its own scale tables.
- Newport: the SMC100 manual: PA/TP/VA/AC/SL/SR are in the stage's units (mm or deg), no
  scaling on the host side; checked by the bytes the driver sends.

The oracle clients are dev dependencies; a test whose client is missing is skipped.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.config import AxisConfig, ControllerConfig
from drivers.sim.clock import ManualClock
from drivers.sim.kinematics import SimAxis
from drivers.sim.server import EmulatorServer

# ---- second sources, by hand ------------------------------------------------------------
XLSM_MICROSTEP_UM = 0.047625
XLSM_TRAVEL_MM = {"X-LSM025A": 25.4, "X-LSM050A": 50.8, "X-LSM100A": 101.6,
                  "X-LSM150A": 152.4, "X-LSM200A": 203.2}
# (counts per unit, velocity register per unit/s, acceleration register per unit/s^2)
APT_DOC = {"MTS25-Z8": (34304.0, 767367.49, 261.93), "MTS50-Z8": (34304.0, 767367.49, 261.93),
           "PRM1-Z8": (1919.64, 42941.66, 14.66), "K10CR1": (136533.0, 7329109.0, 1502.0)}


def zaber_manual(mm: float, mm_s: float, mm_s2: float) -> tuple[int, int, int]:
    steps = mm * 1000 / XLSM_MICROSTEP_UM
    return (round(steps), round(mm_s * 1000 / XLSM_MICROSTEP_UM * 1.6384),
            round(mm_s2 * 1000 / XLSM_MICROSTEP_UM * 1.6384 / 10000))


# ---- Zaber ---------------------------------------------------------------------------------
@pytest.mark.parametrize("stage", sorted(XLSM_TRAVEL_MM))
def test_zaber_driver_and_emulator_units_against_the_manual(stage: str) -> None:
    from drivers.sim.zaber_emu import ZaberEmulator, physics_for
    from drivers.zaber_ascii import make_axes

    clock = ManualClock()
    cfg = {"role": "x", "address": 1, "units": "mm", "stage": stage,
           "soft_limits": {"min": 1.0, "max": XLSM_TRAVEL_MM[stage] - 1.0}, "speed": 5.0,
           "accel": 20.0, "poll_interval_s": 0.05, "backlash_approach": 0.0}
    ax_cfg = AxisConfig.model_validate(cfg)
    sim = SimAxis("x", physics_for(ax_cfg), clock, np.random.default_rng(0), start=10.0)
    emu = ZaberEmulator("platform", {1: sim}, clock)
    steps, speed, accel = zaber_manual(12.3456, 3.0, 15.0)
    assert emu.handle(b"/1 1 get limit.max\n") == \
        b"@01 1 OK IDLE WR %d\r\n" % round(XLSM_TRAVEL_MM[stage] * 1000 / XLSM_MICROSTEP_UM)
    with EmulatorServer(emu, "tcp") as srv:
        ctl = ControllerConfig(name="platform", protocol="zaber", port=srv.url,
                               axes=[{**cfg, "speed": 3.0, "accel": 15.0}])  # type: ignore[list-item]
        (axis,) = make_axes(ctl, clock=clock)
        with axis:
            axis.home()
            axis.move_to(12.3456)
        emu.handle(b"/1 0 set comm.checksum 0\n")  # the driver turned reply checksums on
        got = emu.handle(b"/1 1 get pos\r\n/1 1 get maxspeed\r\n/1 1 get accel\r\n")
    assert got == (b"@01 1 OK IDLE -- %d\r\n@01 1 OK IDLE -- %d\r\n@01 1 OK IDLE -- %d\r\n"
                   % (steps, speed, accel))
    # the emulator's physics follow the manual on their own: 15 mm/s^2 (to 1 LSB of data)
    assert sim.p.accel == pytest.approx(15.0, rel=1 / accel)
    assert sim.motor_position() == pytest.approx(12.3456, abs=XLSM_MICROSTEP_UM / 1000)


def test_zaber_motion_reads_what_the_driver_set_and_is_refused_out_of_range() -> None:
    zm = pytest.importorskip("zaber_motion")
    from zaber_motion.ascii import Connection

    from drivers.sim.clock import ScaledClock
    from drivers.sim.zaber_emu import ZaberEmulator, physics_for
    from drivers.zaber_ascii import make_axes

    clock = ScaledClock(1.0)
    cfgs = [{"role": r, "address": i + 1, "units": "mm", "stage": s,
             "soft_limits": {"min": 1.0, "max": 20.0}, "speed": 5.0, "accel": 20.0}
            for i, (r, s) in enumerate([("x", "X-LSM025A"), ("y", "X-LSM050A"),
                                        ("z", "X-LSM200A")])]
    sims = {i + 1: SimAxis(str(c["role"]), physics_for(AxisConfig.model_validate(c)), clock,
                           np.random.default_rng(i), start=10.0) for i, c in enumerate(cfgs)}
    emu = ZaberEmulator("platform", sims, clock)
    with EmulatorServer(emu, "tcp") as srv:
        ctl = ControllerConfig(name="platform", protocol="zaber", port=srv.url,
                               axes=[{**c, "speed": 3.0, "accel": 15.0} for c in cfgs])  # type: ignore[misc]
        axes = make_axes(ctl)
        for a in axes:
            a.connect()  # writes maxspeed and accel in device units
        for a in axes:
            a.close()
        host, port = srv.url.removeprefix("socket://").rsplit(":", 1)
        with Connection.open_tcp(host, int(port)) as conn:
            devices = conn.detect_devices(identify_devices=False)
            assert [d.device_address for d in devices] == [1, 2, 3]
            _, speed, accel = zaber_manual(0.0, 3.0, 15.0)
            for d in (1, 2, 3):
                assert conn.generic_command("get maxspeed", d, 1).data == str(speed)
                assert conn.generic_command("get accel", d, 1).data == str(accel)
            travel = conn.generic_command("get limit.max", 3, 1).data
            assert int(travel) * XLSM_MICROSTEP_UM / 1000 == pytest.approx(203.2, abs=1e-4)
            bad = conn.generic_command("set accel 68804", 1, 1, check_errors=False)
            assert (bad.reply_flag, bad.data) == ("RJ", "BADDATA")
    assert zm is not None


# ---- Thorlabs APT --------------------------------------------------------------------------
APT_CASES = [("MTS25-Z8", "mm", 2.0, 4.0, 7.5), ("MTS50-Z8", "mm", 2.0, 4.0, 33.0),
             ("PRM1-Z8", "deg", 20.0, 20.0, 45.0), ("K10CR1", "deg", 10.0, 10.0, 30.0)]


@pytest.mark.parametrize(("stage", "units", "speed", "accel", "target"), APT_CASES)
def test_apt_registers_match_the_protocol_documents_table(stage: str, units: str,
                                                          speed: float, accel: float,
                                                          target: float) -> None:
    from drivers import thorlabs_apt as apt

    counts, vel, acc = APT_DOC[stage]
    scale = apt.stage_scale(stage)
    model = scale.controller
    assert scale.counts_per_unit == pytest.approx(counts, rel=1e-5)
    assert apt.velocity_to_register(speed, scale.counts_per_unit, model) == \
        pytest.approx(vel * speed, rel=1e-5)
    assert apt.accel_to_register(accel, scale.counts_per_unit, model) == \
        pytest.approx(acc * accel, rel=2e-4, abs=1)


@pytest.mark.parametrize(("stage", "units", "speed", "accel", "target"), APT_CASES)
def test_pylablib_reads_what_the_driver_set_on_the_emulator(stage: str, units: str,
                                                           speed: float, accel: float,
                                                           target: float) -> None:
    pytest.importorskip("pylablib")
    from pylablib.devices import Thorlabs

    from drivers.sim.apt_emu import AptEmulator, physics_for
    from drivers.sim.clock import ScaledClock
    from drivers.thorlabs_apt import make_axes

    clock = ScaledClock(50.0)
    cfg = {"role": "translator" if units == "mm" else "turntable", "address": 1,
           "units": units, "stage": stage, "speed": speed, "accel": accel,
           "soft_limits": {"min": 0.5, "max": 24.5} if stage == "MTS25-Z8"
           else {"min": 0.5, "max": 49.5} if units == "mm" else {"min": -90.0, "max": 90.0},
           "backlash_approach": 0.0, "deadband": 0.001}
    sim = SimAxis("a", physics_for(AxisConfig.model_validate(cfg)), clock,
                  np.random.default_rng(0), start=10.0)
    emu = AptEmulator("apt", {1: sim}, clock, stage=stage)
    with EmulatorServer(emu, "tcp") as srv:
        ctl = ControllerConfig(name="apt", protocol="apt", port=srv.url,
                               axes=[cfg])  # type: ignore[list-item]
        (axis,) = make_axes(ctl, time_scale=50.0)
        with axis:
            axis.home()
            axis.move_to(target)
        motor = Thorlabs.KinesisMotor(("serial", (srv.url, 115200)), scale="stage")
        try:
            assert motor.get_stage() == stage
            per = 1e3 if units == "mm" else 1.0  # pylablib: m for linear stages, deg else
            vp = motor.get_velocity_parameters()
            assert vp.max_velocity * per == pytest.approx(speed, rel=1e-4)
            assert vp.acceleration * per == pytest.approx(accel, rel=2e-3)
            assert motor.get_position() * per == pytest.approx(target, abs=1.5 / APT_DOC[
                stage][0])
        finally:
            motor.close()
    assert sim.motor_position() == pytest.approx(target, abs=0.001)


# ---- Newport SMC100 ------------------------------------------------------------------------
def test_smc100_sends_positions_speeds_and_limits_in_stage_units() -> None:
    """The SMC100 takes and reports mm or deg as they are (manual: PA, VA, AC, SL, SR):
    the bytes on the wire carry the configured numbers, unscaled."""
    from drivers.newport_smc100 import make_axes
    from drivers.sim.smc100_emu import Smc100Emulator, physics_for

    clock = ManualClock()
    cfg = {"role": "turntable", "address": 1, "units": "deg", "stage": "URS75BCC",
           "soft_limits": {"min": -30.0, "max": 30.0}, "speed": 12.5, "accel": 50.0,
           "backlash_approach": 0.0, "poll_interval_s": 0.01}
    sim = SimAxis("tt", physics_for(AxisConfig.model_validate(cfg)), clock,
                  np.random.default_rng(0), start=0.0)
    emu = Smc100Emulator("turntable", {1: sim}, clock)
    sent: list[bytes] = []
    handle = emu.handle

    def spy(data: bytes) -> bytes:
        sent.append(data)
        return handle(data)

    emu.handle = spy  # type: ignore[method-assign]
    with EmulatorServer(emu, "tcp") as srv:
        ctl = ControllerConfig(name="turntable", protocol="smc100", port=srv.url,
                               axes=[cfg])  # type: ignore[list-item]
        (axis,) = make_axes(ctl, clock=clock)
        with axis:
            assert axis.controller_limits() == (-170.0, 170.0)
            axis.home()
            axis.move_to(12.345)
            assert axis.position() == pytest.approx(12.345, abs=0.001)
    wire = b"".join(sent)
    assert b"1VA12.5\r\n" in wire and b"1AC50\r\n" in wire and b"1PA12.345\r\n" in wire
    assert sim.motor_position() == pytest.approx(12.345, abs=0.001)
