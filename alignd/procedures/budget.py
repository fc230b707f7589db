"""The uncertainty budget of one offset measurement, GUM style.

Each contribution is a covariance of the offset vector (um^2, turntable frame); its standard
uncertainty ``u`` is the root of its trace (both axes together), so the contributions add in
quadrature to the combined ``u_c = sqrt(trace(cov))`` and ``U = k u_c`` with k = 2 is the
run's expanded uncertainty. The contributions:

- centre fit: the pooled centre of rotation's covariance from the solver (type A: from the
  fit residuals of every sweep);
- target point: the scatter of the target point rotated back to angle 0 over the frames;
- pixel scale: the holder-size scale's scatter times the offset;
- residual error motion: what the runout-map correction leaves, the map's own uncertainty
  plus any excess scatter between repeated sweeps (or, with no map, the assumed
  ``procedure.systematic_um``, type B);
- stage repeatability: zero when the verdict's sweep follows the last move (the stages'
  landing scatter is then part of what was measured); it decides whether a move can help.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

COMPONENTS = ("centre fit", "target point", "pixel scale", "residual error motion",
              "stage repeatability")


@dataclass(frozen=True)
class Contribution:
    """One line of the budget."""

    name: str
    u_um: float  # standard uncertainty, both axes: sqrt(trace(cov))
    kind: Literal["A", "B"]  # GUM evaluation type: A statistical, B other knowledge
    basis: str

    def to_dict(self) -> dict[str, object]:
        return {"name": self.name, "u_um": self.u_um, "type": self.kind, "basis": self.basis}


@dataclass(frozen=True)
class Budget:
    """Contributions, combined standard uncertainty, coverage factor, expanded uncertainty."""

    items: tuple[Contribution, ...]
    k: float = 2.0

    @property
    def combined_um(self) -> float:
        return math.sqrt(sum(c.u_um**2 for c in self.items))

    @property
    def U_um(self) -> float:  # noqa: N802 - the contract name
        return self.k * self.combined_um

    def get(self, name: str) -> float:
        return next((c.u_um for c in self.items if c.name == name), 0.0)

    def to_dict(self) -> dict[str, object]:
        return {"contributions": [c.to_dict() for c in self.items],
                "combined_um": self.combined_um, "k": self.k, "U_um": self.U_um}

    def lines(self) -> list[str]:
        """The budget as text, one line per contribution, then u_c and U."""
        out = [f"{c.name:<22} {c.u_um:6.2f} um  ({c.kind}) {c.basis}" for c in self.items]
        out.append(f"{'combined u_c':<22} {self.combined_um:6.2f} um")
        out.append(f"{'expanded U (k=' + format(self.k, 'g') + ')':<22} {self.U_um:6.2f} um")
        return out


def u_of(cov_um2: np.ndarray) -> float:
    """Standard uncertainty of a 2-D contribution: the root of its covariance's trace."""
    return math.sqrt(max(float(np.trace(np.asarray(cov_um2, float))), 0.0))
