"""``alignd-sim --config FILE``: serve every simulated device of a config on its own port.

Prints one JSON line per endpoint (contract), then runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from drivers.config import CameraConfig, ControllerConfig, SimConfig
from drivers.errors import AligndError
from drivers.sim.rig import SimRig


class _RigFile(BaseModel):
    """The parts of an instrument config the simulator needs (the rest is alignd's)."""

    model_config = ConfigDict(extra="ignore")
    controllers: list[ControllerConfig]
    cameras: list[CameraConfig] = []
    sim: SimConfig = SimConfig()


def load_rig_file(path: str) -> _RigFile:
    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.safe_load(fh)
        return _RigFile.model_validate(data)
    except OSError as exc:
        raise SystemExit(f"alignd-sim: {path}: cannot read config: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise SystemExit(f"alignd-sim: {path}: not valid YAML: {exc}") from None
    except ValidationError as exc:
        lines = [f"{path}: {'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()]
        raise SystemExit("alignd-sim: invalid config:\n  " + "\n  ".join(lines)) from None


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="alignd-sim", description=__doc__)
    ap.add_argument("--config", required=True, help="instrument config (YAML)")
    ap.add_argument("--seed", type=int, default=None, help="seed of the simulated world")
    ap.add_argument("--transport", choices=["tcp", "pty", "both"], default="both",
                    help="serve each device on a loopback TCP port, a pty, or both "
                    "(default both)")
    ap.add_argument("--time-scale", type=float, default=None,
                    help="simulated seconds per wall second")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    rig_file = load_rig_file(args.config)
    sim = rig_file.sim
    if args.time_scale is not None:
        if args.time_scale <= 0:
            ap.error("--time-scale must be positive")
        sim = sim.model_copy(update={"time_scale": args.time_scale})
    controllers = [c.model_copy(update={"port": "sim"}) for c in rig_file.controllers]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        rig = SimRig(controllers, rig_file.cameras, sim, seed=args.seed,
                     transport=args.transport)
        with rig:
            for ep in rig.endpoints():
                print(json.dumps(ep), flush=True)
            stop.wait()
    except AligndError as exc:
        print(f"alignd-sim: error: {exc}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
