"""Commissioning benchmark: randomised rig variants, then deliberately wrong configs.

Part 1, variants: each seed builds a simulated rig that differs from the reference in the
ways real rigs do (turntable direction, top camera mirrored or turned by 90/180/270 deg, x/y
roles swapped or inverted, axes not square, holder size and grey level, pixel scale, runout
0-10 um, backlash). Its config is what a user following docs/configure.md writes without
knowing those differences: the holder's size and target as seen in the top image at turntable
0, the camera's nominal pixel size, every convention left at its default. Then, as a user
would: ``commission``; apply the fixes its failing findings name (config keys; for swapped
roles, exchanging x and y); ``commission`` again until it passes; ``align`` with the record.
Target: the true offset within the tolerance on every variant.

Part 2, wrong configs on the reference rig: a reversed turntable, the holder size 10 % off,
the pixel size 20 % off, swapped x/y, an inverted axis. Target: each found and named.

Also printed: how long commissioning takes at real speed (time scale 1), from the simulated
motion time (manual clock) plus a frame time per grabbed frame.

Usage: ``python bench/commission.py [--variants 24] [--quick] [--tracker standin|vision]``.
``standin`` (default) tracks the world's projected corners plus noise in the real tracker's
corner order; ``vision`` renders every frame and runs the real tracker (about 1 min a variant).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from alignd.config import AligndConfig, load_config  # noqa: E402
from alignd.procedures import Tools, default_tools, run_alignment  # noqa: E402
from alignd.procedures.commission import CommissionRecord, run_commission  # noqa: E402
from alignd.simulated import build_direct_rig  # noqa: E402
from alignd.simulated import standin_tools as sim_standin_tools  # noqa: E402
from alignd.vision.holder import order_corners  # noqa: E402
from drivers.sim.render import posed_world  # noqa: E402

FRAME_TIME_S = 1 / 15  # a real camera's frame after a settled move (15 fps), for the estimate
MAX_ROUNDS = 3


def standin_tools(seed: int, sigma_px: float = 0.02) -> Tools:
    """World corners + noise in the real tracker's order (top-left first, clockwise)."""
    return sim_standin_tools(np.random.default_rng(20_000 + seed), sigma_px,
                             f"stand-in (image order) + N(0, {sigma_px} px)")


def with_world(cfg: AligndConfig, **world: object) -> AligndConfig:
    assert cfg.sim is not None
    sim = cfg.sim.model_copy(update={"world": cfg.sim.world.model_copy(update=world)})
    return cfg.model_copy(update={"sim": sim})


def user_holder_config(cfg: AligndConfig, seed: int) -> tuple[tuple[float, float],
                                                             tuple[float, float]]:
    """holder.size_mm and target_mm as a user reads them off the top image at turntable 0
    (docs/configure.md: corner 0 top-left, u to corner 1, v to corner 3): the image axes
    of the holder frame, then the holder's true dimensions along them."""
    assert cfg.sim is not None
    wcfg = cfg.sim.world
    w = posed_world(wcfg, seed=seed)
    cam = w.top_camera
    phys = cam.project(w.top_scene().holder_corners_mm)  # world order: local +x, then +y
    ex, ey = phys[1] - phys[0], phys[3] - phys[0]
    ex, ey = ex / np.hypot(*ex), ey / np.hypot(*ey)
    img = order_corners(phys)
    u = ((img[1] - img[0]) + (img[2] - img[3])) / 2
    v = ((img[3] - img[0]) + (img[2] - img[1])) / 2
    width, depth = wcfg.holder_size_mm
    local_target = (0.0, -(depth / 2 + wcfg.sample_thickness_mm))
    size, target = [], []
    for axis in (u / np.hypot(*u), v / np.hypot(*v)):
        cx, cy = float(axis @ ex), float(axis @ ey)
        if abs(cx) > abs(cy):
            size.append(width)
            target.append(math.copysign(1.0, cx) * local_target[0])
        else:
            size.append(depth)
            target.append(math.copysign(1.0, cy) * local_target[1])
    return (size[0], size[1]), (target[0] + 0.0, target[1] + 0.0)


@dataclass
class Variant:
    seed: int
    world: dict[str, Any]

    def label(self) -> str:
        w = self.world
        bits = []
        if w["turntable_direction"] < 0:
            bits.append("tt-reversed")
        if w["camera_mirror"]:
            bits.append("mirror")
        if w["camera_rotation_deg"]:
            bits.append(f"cam{w['camera_rotation_deg']}")
        if w["swap_xy"]:
            bits.append("xy-swapped")
        if w["invert_x"]:
            bits.append("x-inv")
        if w["invert_y"]:
            bits.append("y-inv")
        bits.append(f"skew{w['stage_skew_deg']:+.1f}")
        bits.append(f"{w['pixel_size_um']:.0f}um/px")
        bits.append(f"holder{w['holder_size_mm'][0]:.0f}x{w['holder_size_mm'][1]:.0f}")
        bits.append("light" if w["holder_dn"] > 100 else "dark")
        bits.append(f"ro{w['wobble_um']:.1f}")
        return " ".join(bits)


def draw_variant(seed: int) -> Variant:
    rng = np.random.default_rng(seed)
    world = {
        "turntable_direction": int(rng.choice([1, -1])),
        "camera_mirror": bool(rng.uniform() < 0.25),
        "camera_rotation_deg": int(rng.choice([0, 90, 180, 270])),
        "swap_xy": bool(rng.uniform() < 0.25),
        "invert_x": bool(rng.uniform() < 0.25),
        "invert_y": bool(rng.uniform() < 0.25),
        "stage_skew_deg": float(rng.uniform(-3.0, 3.0)),
        # inside the rim at every angle (the rim stays measurable, as on the reference rig)
        "holder_size_mm": (float(rng.uniform(30, 40)), float(rng.uniform(18, 25))),
        "holder_dn": float(rng.choice([60.0, 130.0])),
        "pixel_size_um": float(rng.uniform(140, 190)),
        "wobble_um": float(rng.uniform(0, 10)),
        "backlash_mm": float(rng.uniform(0, 0.02)),
        "turntable_backlash_deg": float(rng.uniform(0, 0.01)),
    }
    return Variant(seed, world)


def user_config(base: AligndConfig, v: Variant) -> AligndConfig:
    """The variant's world and the config a user writes for it (conventions unknown)."""
    cfg = with_world(base, **v.world)
    size, target = user_holder_config(cfg, v.seed)
    cams = [c.model_copy(update={"pixel_size_um": v.world["pixel_size_um"]})
            if c.role == "top" else c for c in cfg.cameras]
    # a rim and a holder that fit the image at this scale: the camera sees 1280 x 720 px
    rim = min(50.0, 0.45 * 720 * v.world["pixel_size_um"] / 1000)
    cfg = with_world(cfg, rim_radius_mm=rim)
    return cfg.model_copy(update={
        "cameras": cams,
        "holder": cfg.holder.model_copy(update={"size_mm": size, "target_mm": target}),
        "commission": cfg.commission.model_copy(update={"rim_radius_mm": rim})})


def apply_fixes(cfg: AligndConfig, rec: CommissionRecord) -> tuple[AligndConfig, list[str]]:
    """What a user does with the failing findings: set the keys they name."""
    done: list[str] = []
    fixes: dict[str, Any] = {}
    for f in rec.findings:
        if f.verdict == "fail" and f.config_fix:
            for key, value in f.config_fix.items():
                fixes.setdefault(key, (f.item, value))  # x and y both name a swap: once
    for key, (item, value) in fixes.items():
        if True:
            if key == "holder.size_mm":
                cfg = cfg.model_copy(update={"holder": cfg.holder.model_copy(
                    update={"size_mm": tuple(value)})})
            elif key == "cameras.top.pixel_size_um":
                cfg = cfg.model_copy(update={"cameras": [
                    c.model_copy(update={"pixel_size_um": float(value)}) if c.role == "top"
                    else c for c in cfg.cameras]})
            elif key == "procedure.turntable_direction":
                cfg = cfg.model_copy(update={"procedure": cfg.procedure.model_copy(
                    update={"turntable_direction": int(value)})})
            elif key == "swap_roles":
                # exchanging x and y in the config: the role called x now drives the stage
                # that moves along u (in the simulation: the world's wiring is undone)
                assert cfg.sim is not None
                cfg = with_world(cfg, swap_xy=not cfg.sim.world.swap_xy)
            else:
                continue
            done.append(item)
    return cfg, done


def tools_for(kind: str, seed: int) -> Tools:
    return default_tools() if kind == "vision" else standin_tools(seed)


def commission_once(cfg: AligndConfig, seed: int, tracker: str
                    ) -> tuple[CommissionRecord, float]:
    """One commission run; returns the record and its real-speed time estimate (s)."""
    rig, _ = build_direct_rig(cfg, seed, camera_kind="render" if tracker == "vision"
                              else "scene")
    clock = rig.sim_parts.clock  # type: ignore[attr-defined]
    t0 = clock.now()
    rec = run_commission(rig, cfg, tools=tools_for(tracker, seed))
    motion = clock.now() - t0
    frames = int(rec.details.get("frames", 0))
    return rec, motion + frames * FRAME_TIME_S


def run_variant(base: AligndConfig, v: Variant, tracker: str) -> dict[str, Any]:
    cfg = user_config(base, v)
    findings: list[str] = []
    rounds = 0
    real_s = 0.0
    rec: CommissionRecord | None = None
    while rounds < MAX_ROUNDS:
        rounds += 1
        rec, t = commission_once(cfg, v.seed, tracker)
        real_s = max(real_s, t)
        named = [f"{f.item.split('.')[-2] if f.item.count('.') > 1 else f.item}:"
                 f"{f.name or f.verdict}" for f in rec.findings if f.verdict != "pass"
                 and f.name not in ("not measured", "absent")]
        findings += [n for n in named if n not in findings]
        if rec.verdict != "failed":
            break
        cfg, fixed = apply_fixes(cfg, rec)
        if not fixed:
            break
    assert rec is not None
    out: dict[str, Any] = {"variant": v.label(), "seed": v.seed, "findings": findings,
                           "rounds": rounds, "commission": rec.verdict, "real_s": real_s}
    if rec.verdict != "commissioned":
        out.update(verdict="not commissioned", iterations=0, true_um=math.nan,
                   reason=rec.reason)
        return out
    rig, _ = build_direct_rig(cfg, v.seed, camera_kind="render" if tracker == "vision"
                              else "scene")
    res = run_alignment(rig, cfg, tools=tools_for(tracker, v.seed), commission=rec)
    truth = res.truth or {}
    out.update(verdict=res.verdict, iterations=res.iterations,
               true_um=float(truth.get("offset_norm_um", math.nan)), reason=res.reason)
    return out


WRONG_CONFIGS: list[tuple[str, dict[str, Any], dict[str, Any], str, str]] = [
    # (case, world change, config change, finding item, expected name)
    ("reversed turntable", {"turntable_direction": -1}, {}, "turntable.direction", "reversed"),
    ("holder size 10 % off", {}, {"holder_scale": 1.10}, "holder.size", "holder size wrong"),
    ("pixel size 20 % off", {}, {"pixel_scale": 1.20}, "top.pixel_size", "pixel size wrong"),
    ("x/y swapped", {"swap_xy": True}, {}, "axis.x.direction", "swapped"),
    ("x inverted", {"invert_x": True}, {}, "axis.x.direction", "inverted"),
]


def wrong_config(base: AligndConfig, world: dict[str, Any], change: dict[str, Any]
                 ) -> AligndConfig:
    cfg = with_world(base, **world)
    if "holder_scale" in change:
        k = change["holder_scale"]
        su, sv = cfg.holder.size_mm
        cfg = cfg.model_copy(update={"holder": cfg.holder.model_copy(
            update={"size_mm": (su * k, sv * k)})})
    if "pixel_scale" in change:
        cfg = cfg.model_copy(update={"cameras": [
            c.model_copy(update={"pixel_size_um": (c.pixel_size_um or 160.0)
                                 * change["pixel_scale"]}) if c.role == "top" else c
            for c in cfg.cameras]})
    return cfg


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", type=int, default=24)
    ap.add_argument("--quick", action="store_true", help="3 variants and the wrong configs")
    ap.add_argument("--tracker", choices=["standin", "vision"], default="standin")
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--frames-per-step", type=int, default=1,
                    help="procedure.frames_per_step of every variant's config")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    base = load_config(ROOT / "configs" / "sim.yaml")
    n = 3 if args.quick else args.variants
    tol = base.procedure.tolerance_um
    t_start = time.perf_counter()
    print(f"commission bench: {n} variants, tracker={args.tracker}, tolerance {tol:g} um, "
          f"frames per sweep step {args.frames_per_step}")
    print(f"{'seed':>4}  {'variant':<66} {'rounds':>6} {'iter':>4} {'true um':>8} "
          f"{'verdict':>9}  findings")
    rows = []
    if args.frames_per_step != 1:
        base = base.model_copy(update={"procedure": base.procedure.model_copy(
            update={"frames_per_step": args.frames_per_step})})
    for i in range(n):
        v = draw_variant(args.seed0 + i)
        r = run_variant(base, v, args.tracker)
        rows.append(r)
        print(f"{r['seed']:>4}  {r['variant']:<66} {r['rounds']:>6} {r['iterations']:>4} "
              f"{r['true_um']:>8.2f} {r['verdict']:>9}  {', '.join(r['findings']) or '-'}")
        if r["verdict"] != "aligned" or not r["true_um"] <= tol:
            print(f"      reason: {r['reason']}")
    ok = [r for r in rows if r["verdict"] == "aligned" and r["true_um"] <= tol]
    print()
    print("wrong configs on the reference rig (commission must find and name each):")
    print(f"{'case':<24} {'item':<22} {'verdict':>7} {'named':<20} found")
    found = 0
    for case, world, change, item, name in WRONG_CONFIGS:
        cfg = wrong_config(base, world, change)
        rec, _t = commission_once(cfg, 5, args.tracker)
        f = rec.finding(item)
        hit = f is not None and f.name == name and f.verdict in ("warn", "fail")
        found += hit
        print(f"{case:<24} {item:<22} {f.verdict if f else '-':>7} "
              f"{(f.name if f else '-'):<20} {'yes' if hit else 'NO'}")
        if f is not None:
            print(f"    {f.message[:150]}")
    real = [r["real_s"] for r in rows]
    print()
    print(f"{'metric':<52} {'value':>14} {'target':>10}")
    print(f"{'variants aligned within ' + format(tol, 'g') + ' um (true offset)':<52} "
          f"{len(ok):>5d} of {len(rows):<6d} {'all':>10}")
    tru = [r["true_um"] for r in rows if math.isfinite(r["true_um"])]
    if tru:
        print(f"{'  true offset median / max (um)':<52} {np.median(tru):>6.2f} / "
              f"{max(tru):<5.2f} {'':>10}")
    print(f"{'wrong configs found and named':<52} {found:>5d} of {len(WRONG_CONFIGS):<6d} "
          f"{'all':>10}")
    print(f"{'commission at real speed, est. (s) mean / max':<52} "
          f"{np.mean(real):>6.0f} / {max(real):<5.0f} {'':>10}")
    print(f"  (simulated motion at 1x + {FRAME_TIME_S * 1000:.0f} ms per frame; "
          f"bench wall time {time.perf_counter() - t_start:.0f} s)")
    met = len(ok) == len(rows) and found == len(WRONG_CONFIGS) and len(rows) >= (
        3 if args.quick else 20)
    print(f"\ntargets {'met' if met else 'NOT met'}")
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
