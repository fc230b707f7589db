"""The stage models alignd knows: protocol, units and mechanical travel of each.

Why one table: a config names a stage model per axis, and three things hang on it that
must agree: the driver's unit scale, the soft limits (they must lie inside the travel, or
the stage runs into its end-of-travel switch) and what the controller says it drives. The
drivers keep their own scale tables (counts per unit); this table is what the config is
checked against at load and what a reported identity is compared with at connect.

Travel is from the manufacturers' catalogues: MTS25-Z8 25 mm, MTS50-Z8 50 mm; X-LSM
sizes in inches (X-LSM050A: 2 in = 50.8 mm), from the home sensor at 0; the URS rotation
stages, the PRM1-Z8 and the K10CR1 turn 360 degrees without end (``travel`` None: only
the controller's own limits, read at connect, bound them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Protocol = Literal["smc100", "apt", "zaber"]


@dataclass(frozen=True)
class StageModel:
    """One stage model: which protocol drives it, its units and its travel."""

    name: str
    protocol: Protocol
    units: Literal["mm", "deg"]
    travel: tuple[float, float] | None  # (min, max) in units; None = continuous rotation


def _zaber(name: str, inches: float) -> StageModel:
    return StageModel(name, "zaber", "mm", (0.0, round(inches * 25.4, 6)))


STAGE_MODELS: dict[str, StageModel] = {m.name: m for m in (
    StageModel("URS75BCC", "smc100", "deg", None),
    StageModel("URS100BCC", "smc100", "deg", None),
    StageModel("URS150BCC", "smc100", "deg", None),
    StageModel("MTS25-Z8", "apt", "mm", (0.0, 25.0)),
    StageModel("MTS50-Z8", "apt", "mm", (0.0, 50.0)),
    StageModel("PRM1-Z8", "apt", "deg", None),
    StageModel("K10CR1", "apt", "deg", None),
    _zaber("X-LSM025A", 1.0),
    _zaber("X-LSM050A", 2.0),
    _zaber("X-LSM100A", 4.0),
    _zaber("X-LSM150A", 6.0),
    _zaber("X-LSM200A", 8.0),
)}

# What an APT axis without a stage name drives (the driver's default, kept here too).
APT_DEFAULT_STAGE = {"mm": "MTS25-Z8", "deg": "K10CR1"}


def known_models(protocol: str) -> list[str]:
    return sorted(m.name for m in STAGE_MODELS.values() if m.protocol == protocol)


def lookup(name: str, protocol: str | None = None) -> StageModel | None:
    """The model ``name`` names (case-insensitive; a Zaber suffix such as ``-E03`` or a
    Thorlabs ``/M`` is allowed), or None. With ``protocol``, only that protocol's models."""
    key = name.strip().upper().replace("/M", "")
    candidates = [m for m in STAGE_MODELS.values()
                  if protocol is None or m.protocol == protocol]
    for m in candidates:
        if key == m.name:
            return m
    for m in sorted(candidates, key=lambda m: len(m.name), reverse=True):
        if m.protocol == "zaber" and key.startswith(m.name + "-"):
            return m
    return None


def resolve(protocol: str, stage: str, units: str) -> StageModel | None:
    """The model an axis config means; None for an SMC100 axis without a stage name
    (the SMC100 scales nothing by stage; its limits are read from the controller), and for
    a plug-in protocol this catalogue has no models of (its stages are its own business;
    the identity and limit checks at connect still apply).
    ``ValueError`` with the known models for a name this protocol does not know."""
    if not known_models(protocol):
        return None
    if not stage and protocol == "apt":
        stage = APT_DEFAULT_STAGE[units]
    if not stage and protocol == "smc100":
        return None
    model = lookup(stage, protocol)
    if model is None:
        other = lookup(stage) if stage else None
        hint = (f" ({other.name} is a {other.protocol} stage)" if other is not None else "")
        raise ValueError(f"unknown {protocol} stage model {stage!r}{hint}; known: "
                         f"{', '.join(known_models(protocol))}")
    return model
