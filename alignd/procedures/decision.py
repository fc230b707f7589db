"""The decision rule: when does a measured offset with its uncertainty say "within tolerance"?

The measurand is the distance of the target point from the mean axis of rotation (the axis
averaged over a turn), ``|offset|``, with ``U`` the expanded uncertainty (k = 2) of the
offset vector (2 sqrt(trace(cov)): the true target lies within U of the measured one with at
least 95 % probability). Two rules (``procedure.decision_rule``):

- ``guarded`` (default), guarded acceptance per ISO 14253-1: conformance is proven when the
  measured distance is at most the tolerance minus a guard band equal to U; nonconformance
  is proven when it is at least the tolerance plus U; in between the measurement cannot
  decide (the procedure then measures better or moves, never guesses).
- ``simple``, simple acceptance (ILAC-G8, ISO/IEC Guide 98-4 with no guard band): within
  when the measured distance is at most the tolerance. Cheaper, and the risk of a false
  "within" near the limit is up to 50 %. A measurement whose U is not below the tolerance
  itself decides nothing, under either rule.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Rule = Literal["guarded", "simple"]
Outcome = Literal["conforms", "does_not_conform", "undecided"]

RULE_NAMES: dict[str, str] = {
    "guarded": "guarded acceptance, ISO 14253-1 (guard band = U)",
    "simple": "simple acceptance (no guard band)",
}


@dataclass(frozen=True)
class Decision:
    """One verdict on one measurement, with everything needed to explain it."""

    rule: Rule
    tolerance_um: float
    offset_um: float  # measured distance from the mean axis
    U_um: float
    guard_band_um: float
    outcome: Outcome

    @property
    def accept_below_um(self) -> float:
        """Measured distances up to this are accepted (acceptance zone)."""
        return self.tolerance_um - self.guard_band_um

    @property
    def reject_above_um(self) -> float:
        """Measured distances from this on are rejected (rejection zone)."""
        return self.tolerance_um + self.guard_band_um

    @property
    def conforms(self) -> bool:
        return self.outcome == "conforms"

    @property
    def margin_um(self) -> float:
        """How far the measurement is inside its zone's edge (negative: undecided)."""
        if self.outcome == "conforms":
            return self.accept_below_um - self.offset_um
        if self.outcome == "does_not_conform":
            return self.offset_um - self.reject_above_um
        return -min(self.offset_um - self.accept_below_um,
                    self.reject_above_um - self.offset_um)

    def text(self) -> str:
        """The operator's line: "within 10 um: offset 2.1 um, U 3.4 um, guard band 3.4 um
        (accept below 6.6 um; guarded acceptance, ISO 14253-1 ...)"."""
        head = {"conforms": f"within {self.tolerance_um:g} um",
                "does_not_conform": f"beyond {self.tolerance_um:g} um",
                "undecided": f"undecided against {self.tolerance_um:g} um"}[self.outcome]
        if self.rule == "guarded":
            zone = (f"guard band {self.guard_band_um:.1f} um (accept up to "
                    f"{self.accept_below_um:.1f} um, reject from {self.reject_above_um:.1f} um)")
        elif self.U_um >= self.tolerance_um:
            zone = "no guard band, but U is not below the tolerance"
        else:
            zone = "no guard band (accept up to the tolerance)"
        return (f"{head}: offset {self.offset_um:.1f} um, U {self.U_um:.1f} um (k=2), {zone}; "
                f"{RULE_NAMES[self.rule]}")

    def to_dict(self) -> dict[str, object]:
        return {"rule": self.rule, "rule_name": RULE_NAMES[self.rule],
                "tolerance_um": self.tolerance_um, "offset_um": self.offset_um,
                "U_um": self.U_um, "guard_band_um": self.guard_band_um,
                "accept_below_um": self.accept_below_um,
                "reject_above_um": self.reject_above_um, "outcome": self.outcome,
                "text": self.text()}


def decide(offset_um: float, U_um: float, tolerance_um: float,
           rule: Rule = "guarded") -> Decision:
    """Apply the decision rule to a measured distance and its expanded uncertainty."""
    if rule == "guarded":
        g = U_um
        if offset_um <= tolerance_um - g:
            outcome: Outcome = "conforms"
        elif offset_um >= tolerance_um + g:
            outcome = "does_not_conform"
        else:
            outcome = "undecided"
    elif rule == "simple":
        g = 0.0
        if U_um >= tolerance_um:
            outcome = "undecided"
        else:
            outcome = "conforms" if offset_um <= tolerance_um else "does_not_conform"
    else:
        raise ValueError(f"unknown decision rule {rule!r} (guarded or simple)")
    return Decision(rule, float(tolerance_um), float(offset_um), float(U_um), float(g),
                    outcome)


def U_needed(offset_um: float, tolerance_um: float) -> float:  # noqa: N802
    """The largest U with which the guarded rule decides at this measured distance."""
    return abs(tolerance_um - offset_um)
