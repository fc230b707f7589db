"""The result of one run, and its JSON per the run-result contract (DESIGN.md).

Contract keys: ``run_id``, ``verdict``, ``offset_um`` ([x, y], turntable frame),
``offset_norm_um``, ``U_um`` (expanded uncertainty, k = 2), ``iterations``, ``tilt_deg``,
``yaw_deg``, ``reason``; ``tilt_u_deg`` (the tilt's standard uncertainty, k = 1, from
the pre-check's frames), ``eccentricity`` (the top camera's rim pre-check) and
``eccentricity_u`` (its standard uncertainty, k = 1, from the mean of its frames); since the
decisive-verdicts release also ``sweeps`` (measurements; ``iterations`` counts correction
moves), ``decision`` (the rule, guard band, zones and the
operator's line) and ``budget`` (the uncertainty budget, um); on a simulated rig also
``truth`` (``offset_um``, ``offset_norm_um``) read from the simulator after the run, never
by the loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

Verdict = Literal["aligned", "within_tolerance", "out_of_tolerance", "not_converged",
                  "aborted", "fault"]
VERDICTS: tuple[Verdict, ...] = get_args(Verdict)

# contract: exit codes. 0 ok / within tolerance, 1 out of tolerance or not converged
# (an aborted run did not reach its goal either), 2 usage or config error, 3 fault.
EXIT_CODES: dict[str, int] = {"aligned": 0, "within_tolerance": 0, "out_of_tolerance": 1,
                              "not_converged": 1, "aborted": 1, "fault": 3}


def _num(x: float | None, nd: int = 3) -> float | None:
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), nd)


@dataclass
class RunResult:
    """Outcome of ``run_alignment`` / ``run_check``; ``details`` holds the full record."""

    run_id: str
    mode: Literal["align", "check"]
    verdict: Verdict
    reason: str = ""
    offset_um: tuple[float, float] | None = None
    U_um: float | None = None
    iterations: int = 0  # correction moves
    sweeps: int = 0  # measurement sweeps
    tilt_deg: float | None = None
    tilt_u_deg: float | None = None  # standard uncertainty of tilt_deg (k = 1)
    eccentricity: float | None = None  # the top camera's rim pre-check (apparent e)
    eccentricity_u: float | None = None  # standard uncertainty of eccentricity (k = 1)
    yaw_deg: float | None = None
    truth: dict[str, Any] | None = None
    config_error: bool = False  # the fault was a config problem (exit code 2)
    budget: dict[str, Any] | None = None
    decision: dict[str, Any] | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.verdict not in VERDICTS:
            raise ValueError(f"unknown verdict {self.verdict!r}")

    @property
    def offset_norm_um(self) -> float | None:
        return None if self.offset_um is None else float(math.hypot(*self.offset_um))

    @property
    def ok(self) -> bool:
        return self.verdict in ("aligned", "within_tolerance")

    @property
    def exit_code(self) -> int:
        if self.verdict == "fault" and self.config_error:
            return 2
        return EXIT_CODES[self.verdict]

    def to_json(self) -> dict[str, Any]:
        """The run-result contract object (JSON-ready: floats, lists, None)."""
        off = None if self.offset_um is None else [_num(v) for v in self.offset_um]
        out: dict[str, Any] = {
            "run_id": self.run_id,
            "verdict": self.verdict,
            "offset_um": off,
            "offset_norm_um": _num(self.offset_norm_um),
            "U_um": _num(self.U_um),
            "iterations": int(self.iterations),
            "tilt_deg": _num(self.tilt_deg, 4),
            "tilt_u_deg": _num(self.tilt_u_deg, 5),
            "eccentricity": _num(self.eccentricity, 4),
            "eccentricity_u": _num(self.eccentricity_u, 5),
            "yaw_deg": _num(self.yaw_deg, 4),
            "reason": self.reason,
            "sweeps": int(self.sweeps),
        }
        if self.decision is not None:
            out["decision"] = {k: (_num(v) if isinstance(v, float) else v)
                               for k, v in self.decision.items()}
        if self.budget is not None:
            out["budget"] = {
                "contributions": [{**c, "u_um": _num(c["u_um"])}
                                  for c in self.budget["contributions"]],
                "combined_um": _num(self.budget["combined_um"]), "k": self.budget["k"],
                "U_um": _num(self.budget["U_um"])}
        if self.truth is not None:
            t_off = [float(v) for v in self.truth["offset_um"]]
            out["truth"] = {"source": "simulator (read after the run, never by the loop)",
                            "offset_um": [_num(v) for v in t_off],
                            "offset_norm_um": _num(math.hypot(*t_off))}
        return out

    def to_dict(self) -> dict[str, Any]:
        """The contract object plus mode and the full details (for the run record)."""
        return {**self.to_json(), "mode": self.mode, "details": self.details}
