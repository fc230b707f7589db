"""One registry of stage protocols: the config's names come from it, the simulator and the
hardware factory look drivers/emulators/physics up in it, and a plug-in adds a protocol
through the ``alignd.protocols`` entry-point group."""

from __future__ import annotations

import logging
import textwrap
from collections.abc import Iterator, Sequence
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest
import yaml

from alignd.config import ConfigError, load_config, parse_config
from alignd.hardware import open_rig
from drivers import registry
from drivers.axis import Axis
from drivers.clock import Clock
from drivers.config import ControllerConfig

SIM = Path(__file__).resolve().parent.parent / "configs" / "sim.yaml"

# A plug-in's module: a new protocol name for an SMC100-compatible controller (the
# "one module plus one registration" a new stage needs); its driver and emulator are the
# SMC100 ones, reached through the registry like any other.
PLUGIN = textwrap.dedent('''
    from drivers import registry
    from drivers.newport_smc100 import make_axes as smc100_axes
    from drivers.sim.smc100_emu import Smc100Emulator, physics_for


    def make_axes(controller, time_scale=1.0, *, clock=None):
        return smc100_axes(controller.model_copy(update={"protocol": "smc100"}), time_scale,
                           clock=clock)


    PROTOCOL = registry.StageProtocol("acme", lambda: make_axes, lambda: Smc100Emulator,
                                      lambda: physics_for, "ACME rotator (SMC100 dialect)")
    NOT_A_PROTOCOL = 42
''')


@pytest.fixture
def plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """The plug-in module on sys.path and its entry points in the group."""
    (tmp_path / "acme_alignd.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = [EntryPoint("acme", "acme_alignd:PROTOCOL", registry.ENTRY_POINT_GROUP),
           EntryPoint("broken", "acme_alignd:NOT_A_PROTOCOL", registry.ENTRY_POINT_GROUP),
           EntryPoint("missing", "no_such_module_xyz:P", registry.ENTRY_POINT_GROUP)]
    monkeypatch.setattr(registry, "entry_points",
                        lambda group: [e for e in eps if e.group == group])
    try:
        yield "acme"
    finally:
        registry.unregister("acme")


def sim_config_with(protocol: str) -> dict[str, object]:
    data = yaml.safe_load(SIM.read_text())
    data["controllers"][0]["protocol"] = protocol
    return data


def test_builtin_protocols_are_the_configs_allowed_names() -> None:
    assert registry.names()[:3] == ("smc100", "apt", "zaber")
    assert all(registry.get(n).simulated for n in ("smc100", "apt", "zaber"))
    with pytest.raises(ConfigError, match=r"controllers\.0\.protocol: .*unknown protocol "
                       r"'acme'; known: smc100, apt, zaber"):
        parse_config(sim_config_with("acme"), "rig.yaml")
    with pytest.raises(registry.UnknownProtocolError, match="unknown protocol 'acme'"):
        registry.get("acme")


def test_a_plugin_protocol_is_registered_configured_simulated_and_driven(
        plugin: str, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.ERROR, logger="drivers.registry"):
        assert registry.load_entry_points() == ["acme"]
    # the broken entry points are named in the log, the good one still loads
    assert "broken" in caplog.text and "not a drivers.registry.StageProtocol" in caplog.text
    assert "missing" in caplog.text
    assert "acme" in registry.names()
    cfg = parse_config(sim_config_with("acme"), "rig.yaml")
    assert cfg.controllers[0].protocol == "acme"
    # port: sim serves it with the registered emulator; the registered driver talks to it
    rig = open_rig(cfg.model_copy(update={"sim": cfg.sim.model_copy(  # type: ignore[union-attr]
        update={"time_scale": 50.0})}), seed=3)
    try:
        tt = rig.axis("turntable")
        tt.connect()
        assert tt.identify().vendor == "Newport"
        tt.home()
        assert tt.move_to(3.5) == pytest.approx(3.5, abs=tt.config.deadband)
    finally:
        rig.close()


def test_register_refuses_a_taken_or_bad_name() -> None:
    smc = registry.get("smc100")
    with pytest.raises(ValueError, match="already registered"):
        registry.register(smc)
    with pytest.raises(ValueError, match="plain identifier"):
        registry.register(registry.StageProtocol("no spaces", smc.driver))


def test_a_protocol_without_emulator_cannot_be_port_sim() -> None:
    def driver() -> registry.AxesFactory:
        def make(controller: ControllerConfig, time_scale: float = 1.0, *,
                 clock: Clock | None = None) -> Sequence[Axis]:
            raise AssertionError("not reached")

        return make

    registry.register(registry.StageProtocol("hwonly", driver))
    try:
        with pytest.raises(ConfigError, match=r"controllers\.0: .*protocol 'hwonly' has no "
                           "emulator: use a real port, not 'sim'"):
            parse_config(sim_config_with("hwonly"), "rig.yaml")
        hw = sim_config_with("hwonly")
        hw["controllers"][0]["port"] = "/dev/ttyUSB9"  # type: ignore[index]
        assert parse_config(hw, "rig.yaml").controllers[0].protocol == "hwonly"
    finally:
        registry.unregister("hwonly")


def test_reference_config_still_loads() -> None:
    assert [c.protocol for c in load_config(SIM).controllers] == ["smc100", "apt", "zaber"]
