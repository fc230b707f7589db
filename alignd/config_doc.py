"""The config reference and JSON Schema, generated from the pydantic models.

``docs/config-reference.md`` and ``docs/alignd-config.schema.json`` are written by
``alignd --config-reference`` / ``--config-schema`` and a test keeps them current: the
models are the one source of every key, unit, default and bound.
"""

from __future__ import annotations

import json
import types
import typing
from typing import Any, Literal, get_args, get_origin

from annotated_types import Ge, Gt, Le, Lt, MaxLen, MinLen
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from alignd.config import AligndConfig, check_config_file

__all__ = ["check_config_file", "json_schema", "reference_markdown"]

UNITS = {"_deg_s": "deg/s", "_hz": "Hz", "_um": "um", "_mm": "mm", "_deg": "deg", "_s": "s",
         "_px": "px", "_dn": "DN"}


# meanings of keys whose model field carries no description (kept here rather than
# in every model line; a model description, where there is one, wins)
MEANINGS = {
    "version": "config format version; always 1",
    "name": "instrument name, shown by status and in reports",
    "controllers": "the motion controllers, one per serial port",
    "cameras": "the cameras: a top one (required) and a side one",
    "holder": "the sample holder as the top camera sees it",
    "procedure": "the alignment loop",
    "commission": "alignctl commission",
    "daemon": "the daemon: socket, permissions, records",
    "sim": "the simulated rig (used where a port or source is 'sim')",
    "controllers[].name": "a name for the controller (unique; used in messages)",
    "controllers[].protocol": "smc100: Newport SMC100; apt: Thorlabs APT (KDC101, ...); "
                              "zaber: Zaber ASCII",
    "controllers[].baudrate": "null: the protocol's standard rate (57600 / 115200 / 115200)",
    "controllers[].reply_timeout_s": "how long to wait for a reply before retrying",
    "controllers[].axes": "the axes this controller drives",
    "controllers[].axes[].role": "what the axis does in the procedure",
    "controllers[].axes[].units": "deg for the turntable, mm for the linear stages",
    "controllers[].axes[].soft_limits": "travel alignd never commands beyond (required)",
    "controllers[].axes[].soft_limits.min": "lowest allowed target",
    "controllers[].axes[].soft_limits.max": "highest allowed target",
    "controllers[].axes[].retries": "re-sends of a move whose read-back missed the deadband",
    "controllers[].axes[].approach": "every move arrives moving this way (backlash)",
    "controllers[].axes[].stall_timeout_s": "no motion for this long during a move is a stall",
    "controllers[].axes[].poll_interval_s": "status polling interval during a move",
    "controllers[].axes[].home_timeout_s": "longest a homing run may take",
    "cameras[].role": "top (looks down the axis) or side (along the sample surface)",
    "cameras[].width": "requested frame width (null: the camera's default)",
    "cameras[].height": "requested frame height (null: the camera's default)",
    "cameras[].exposure": "exposure as the camera backend takes it (null: automatic)",
    "cameras[].pixel_size_um": "image scale at the holder's top face; commission measures it",
    "holder.size_mm": "[u, v]: the holder's top face along corner 0 -> 1 and 0 -> 3 "
                      "(docs/configure.md)",
    "holder.target_mm": "[u, v]: the middle of the sample surface from the holder's centre",
    "procedure.sweep_steps": "frames per sweep",
    "procedure.tolerance_um": "how close to the axis the target must be",
    "procedure.max_iterations": "sweeps before giving up (align) or deciding (check)",
    "procedure.max_step_mm": "largest correction move of one axis",
    "procedure.max_center_sigma_um": "no move on a centre less certain than this",
    "procedure.calibration_step_mm": "length of the calibration moves",
    "procedure.correction_axes": "the two stages that move the sample across the axis",
    "procedure.precheck": "checks before anything moves",
    "procedure.precheck.max_eccentricity": "rim ellipse eccentricity above which the top "
                                           "camera is not on the axis",
    "procedure.precheck.max_tilt_deg": "sample tilt (side camera) above which it is refused",
    "procedure.precheck.action": "warn: note it and go on; refuse: stop before moving",
    "daemon.socket": "control socket path",
    "daemon.operator_group": "group whose members may start, abort and reset (null: none)",
    "daemon.watchdog": "use systemd's watchdog when started with one",
    "sim.seed": "seed of the simulated misalignment, noise and imperfections",
    "sim.time_scale": "simulated time runs this much faster than real time",
    "sim.transport": "serve the emulators on TCP ports, ptys or both",
    "sim.world": "geometry and imperfections of the simulated world",
    "sim.faults": "injected faults (tests, soak benchmark)",
    "sim.faults[].device": "controller name",
    "sim.faults[].kind": "what goes wrong",
    "sim.faults[].probability": "chance per command",
    "sim.faults[].delay_s": "delay of slow and late replies",
    "sim.faults[].axis": "the axis a stall or limit hits",
    "sim.world.axis_px": "where the rotation axis is imaged (px)",
    "sim.world.pixel_size_um": "top camera scale at the turntable plane",
    "sim.world.holder_size_mm": "true holder size (width along x, depth along y)",
    "sim.world.rim_radius_mm": "turntable rim radius",
    "sim.world.sample_thickness_mm": "sample thickness in front of the holder",
    "sim.world.initial_offset_mm": "target offset at mid-travel (null: random from the seed)",
    "sim.world.initial_offset_max_mm": "largest random initial offset",
    "sim.world.yaw_deg": "sample yaw (null: random 1-2 deg)",
    "sim.world.stage_skew_deg": "non-squareness of the platform's x and y",
    "sim.world.translator_skew_deg": "translator direction against the sample normal",
    "sim.world.tilt_deg": "sample tilt seen by the side camera",
    "sim.world.wobble_um": "turntable radial error motion (harmonics 2 and 3), 0-50",
    "sim.world.stage_repeatability_um": "landing scatter of the linear stages",
    "sim.world.backlash_mm": "dead zone of the linear stages",
    "sim.world.turntable_backlash_deg": "dead zone of the turntable",
    "sim.world.turntable_encoder_error_deg": "periodic encoder error (third harmonic)",
    "sim.world.top_camera_zenith_deg": "top camera tilt from the axis",
    "sim.world.noise_dn": "sensor read noise",
}


def _unit(name: str) -> str:
    for suffix, unit in UNITS.items():
        if name.endswith(suffix):
            return unit
    return ""


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is typing.Annotated:  # a constrained member of a union: its bounds with it
        base, *meta = get_args(tp)
        bounds = _bounds_of(meta)
        return f"{_type_name(base)} ({bounds})" if bounds else _type_name(base)
    if origin is Literal:
        return " \\| ".join(json.dumps(a) for a in get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a) for a in get_args(tp))
    if origin in (list, tuple):
        args = [a for a in get_args(tp) if a is not Ellipsis]
        inner = ", ".join(_type_name(a) for a in args)
        return f"[{inner}]" if origin is tuple else f"list of {inner}"
    if tp is type(None):
        return "null"
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return "mapping"
    return getattr(tp, "__name__", str(tp))


def _bounds(info: FieldInfo) -> str:
    return _bounds_of(info.metadata)


def _bounds_of(metadata: list[Any]) -> str:
    parts = []
    for m in metadata:
        if isinstance(m, FieldInfo):  # Annotated[..., Field(ge=...)]: its own metadata
            parts += [p for p in [_bounds_of(m.metadata)] if p]
            continue
        if isinstance(m, Ge):
            parts.append(f">= {m.ge}")
        elif isinstance(m, Gt):
            parts.append(f"> {m.gt}")
        elif isinstance(m, Le):
            parts.append(f"<= {m.le}")
        elif isinstance(m, Lt):
            parts.append(f"< {m.lt}")
        elif isinstance(m, MinLen):
            parts.append(f"at least {m.min_length} item(s)")
        elif isinstance(m, MaxLen):
            parts.append(f"at most {m.max_length} item(s)")
    return ", ".join(parts)


def _default(info: FieldInfo) -> str:
    if info.is_required():
        return "**required**"
    if info.default_factory is not None:
        return "`[]`"
    d = info.default
    if d is PydanticUndefined:
        return ""
    if isinstance(d, BaseModel):
        return "(section)"
    return f"`{json.dumps(d)}`"


def _models(tp: Any) -> list[type[BaseModel]]:
    """The models inside a field's type (a section, a list of items, an optional one)."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return [tp]
    out: list[type[BaseModel]] = []
    for a in get_args(tp):
        out += _models(a)
    return out


def _rows(model: type[BaseModel], prefix: str, rows: list[str]) -> None:
    nested: list[tuple[str, type[BaseModel]]] = []
    for name, info in model.model_fields.items():
        key = f"{prefix}{name}"
        desc = (info.description or MEANINGS.get(key.strip("*"), "")).replace(
            "|", "\\|").replace("\n", " ")
        rows.append(f"| `{key}` | {_type_name(info.annotation)} | {_unit(name)} | "
                    f"{_default(info)} | {_bounds(info)} | {desc} |")
        for sub in _models(info.annotation):
            is_list = get_origin(info.annotation) is list
            nested.append((f"{key}[]." if is_list else f"{key}.", sub))
    for p, sub in nested:
        rows.append(f"| **{p.rstrip('.')}** | | | | | {_first_line(sub.__doc__) or '-'} |")
        _rows(sub, p, rows)


def _first_line(doc: str | None) -> str:
    return (doc or "").strip().split("\n\n")[0].replace("\n", " ").replace("|", "\\|")


def reference_markdown() -> str:
    """Every key of the instrument config: type, unit, default, bounds, meaning."""
    rows: list[str] = []
    _rows(AligndConfig, "", rows)
    head = [
        "# Config reference",
        "",
        "<!-- generated by `alignd --config-reference` from alignd/config.py and "
        "drivers/config.py; a test keeps it current: do not edit by hand -->",
        "",
        "Every key of the instrument config (one YAML file; unknown keys are refused). "
        "Units are in the key names (`_mm`, `_um`, `_deg`, `_s`). Validate a file without "
        "touching hardware: `alignd --check-config FILE`. Editors that read JSON Schema "
        "(VS Code with the YAML extension, IntelliJ) complete and check keys with "
        "[`alignd-config.schema.json`](alignd-config.schema.json): put "
        "`# yaml-language-server: $schema=<path>/alignd-config.schema.json` on the first "
        "line of the config.",
        "",
        "| key | type | unit | default | bounds | meaning |",
        "|---|---|---|---|---|---|",
    ]
    return "\n".join(head + rows) + "\n"


def json_schema() -> str:
    """JSON Schema (draft 2020-12) of the config, for editors."""
    schema = AligndConfig.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "alignd instrument config"
    return json.dumps(schema, indent=2, sort_keys=True) + "\n"
