"""alignd as a Bluesky device (``pip install 'alignd[bluesky]'``): an ophyd-async device.

    from bluesky import RunEngine, plans as bp
    from alignd.ophyd_device import AligndDevice

    RE = RunEngine()
    check = AligndDevice("/run/alignd/alignd.sock", kind="check", name="alignd_check")
    RE(bp.count([check]))        # trigger: a check through alignd.client; read: the result

``trigger()`` starts a run of ``kind`` (``check``: measure only, or ``align``: closed
loop) on the daemon and completes when the run ends; the status fails when the run ended
in ``fault`` or ``aborted`` (out of tolerance or not converged are readings, not errors).
``read()`` gives ``offset_um`` (|offset|), ``offset_x_um``/``offset_y_um`` (turntable
frame), ``uncertainty_um`` (U, k = 2), ``verdict``, ``within_tolerance`` and ``run_id``.
``stop()`` aborts the run in progress (every axis stops). Control rights are the daemon's:
the user running the RunEngine must be allowed to control alignd (operator group).

Why through ``alignd.client`` and not the hardware: the daemon owns the devices and keeps
the record of every run; a Bluesky plan is one more client of it.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Literal

from ophyd_async.core import AsyncStatus, StandardReadable, soft_signal_r_and_setter

from alignd.client import Client, RunResult
from alignd.errors import AligndError


class AligndRunFailed(AligndError):
    """The run a trigger started ended in fault or was aborted."""


class AligndDevice(StandardReadable):
    """Triggerable, readable, stoppable: one alignd run per trigger."""

    def __init__(self, socket_path: str | Path | None = None,
                 kind: Literal["check", "align"] = "check", name: str = "",
                 started_by: str = "user") -> None:
        if kind not in ("check", "align"):
            raise ValueError(f"kind must be 'check' or 'align', not {kind!r}")
        self.kind = kind
        self.started_by = started_by
        self._client = Client(socket_path)
        with self.add_children_as_readables():
            self.offset_um, self._set_offset = soft_signal_r_and_setter(float, units="um")
            self.offset_x_um, self._set_x = soft_signal_r_and_setter(float, units="um")
            self.offset_y_um, self._set_y = soft_signal_r_and_setter(float, units="um")
            self.uncertainty_um, self._set_u = soft_signal_r_and_setter(float, units="um")
            self.verdict, self._set_verdict = soft_signal_r_and_setter(str)
            self.within_tolerance, self._set_ok = soft_signal_r_and_setter(bool)
            self.run_id, self._set_run = soft_signal_r_and_setter(int)
        self.last_result: RunResult | None = None
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        run = self._client.check if self.kind == "check" else self._client.align
        result: RunResult = await asyncio.to_thread(run, True, started_by=self.started_by)
        self.last_result = result
        nan = float("nan")
        self._set_run(result.run_id)
        self._set_verdict(result.verdict)
        self._set_ok(result.ok)
        self._set_offset(nan if result.offset_norm_um is None else result.offset_norm_um)
        x, y = result.offset_um if result.offset_um is not None else (nan, nan)
        self._set_x(x)
        self._set_y(y)
        self._set_u(nan if result.U_um is None else result.U_um)
        if result.verdict in ("fault", "aborted"):
            raise AligndRunFailed(f"alignd {self.kind} run {result.run_id} ended "
                                  f"{result.verdict}: {result.reason}")

    async def stop(self, success: bool = True) -> None:
        """Abort the run in progress (no-op when none is)."""
        await asyncio.to_thread(self._client.abort)
