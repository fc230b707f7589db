"""Which side of the holder the sample is on, read from the swept axis.

``holder.target_mm`` is typed in the holder frame the top image numbers (docs/configure.md).
A top camera turned 180 deg from the one the config was written against, or a holder
mounted the other way round, puts the target on the holder's far side: a run then chased a
point 35 mm off the axis, 5 mm a move, and ended "not converged" without saying why. A
quarter turn does the same to a square holder; a non-square one shows it in its sides'
lengths (the swapped frame, which names two targets a symmetric rectangle cannot tell
apart).

The sweep tells them apart. A lab puts the sample near the axis by hand before a run, so a
configured target far from the axis whose turned image lies near it names the config as
wrong, before any correction move is made on it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from alignd.config import HolderConfig
from alignd.errors import HolderFrameError
from alignd.procedures.angles import SQUARE_WITHIN, ReferenceOrder
from alignd.procedures.holder_geometry import holder_poses, rot, turned

# a turned target within this fraction of |target_mm| of the axis is where the sample is
NEAR_FRACTION = 0.3
# a target nearer the holder's centre than this (mm): its sides are too close to tell
MIN_TARGET_MM = 2.0


@dataclass(frozen=True)
class TargetCandidate:
    target_mm: tuple[float, float]  # in the holder frame the image numbers
    offset_mm: float  # its distance from the axis at turntable 0
    quarter_turns: int  # from the configured target
    offset_px: np.ndarray  # from the axis at turntable 0, in the sweep's image


# the sweep's points -> the camera's image (the sweep is measured rectified)
ToImage = Callable[[np.ndarray], np.ndarray]


def candidate_offsets(points: np.ndarray, angles_deg: np.ndarray | list[float],
                      centre_px: np.ndarray, holder: HolderConfig,
                      quarter_turns: tuple[int, ...]) -> list[TargetCandidate]:
    """How far each turned ``holder.target_mm`` lies from the axis at ``centre_px``: every
    tracked frame's point turned back about the centre by its angle (image convention),
    averaged, in mm at the holder's own scale."""
    p = np.asarray(points, float)
    ok = np.flatnonzero(np.all(np.isfinite(p), axis=(1, 2)))
    poses = holder_poses(p[ok], holder)
    back = rot(-np.asarray(angles_deg, float)[ok])
    scale = float(poses.scale_px_per_mm.mean())
    c = np.asarray(centre_px, float)
    out = []
    for k in quarter_turns:
        t = turned(holder.target_mm, k)
        off = np.einsum("nij,nj->ni", back, poses.at(t) - c).mean(axis=0)
        out.append(TargetCandidate(t, float(np.hypot(*off)) / scale, k, off))
    return out


def _evidence(centre_px: np.ndarray, to_image: ToImage,
              drawn: list[tuple[TargetCandidate, str]]) -> dict[str, object]:
    """What the run's picture draws (report.py): the axis and each target's offset from
    it at turntable 0 in the camera's image, with its label and role ("config": the
    configured target, "fix": the one the message names)."""
    c = np.asarray(centre_px, float)
    ci = to_image(c[None])[0]
    return {"centre_px": [float(v) for v in ci], "targets": [
        {"role": role, "target_mm": list(t.target_mm), "offset_mm": t.offset_mm,
         "offset_px": [float(v) for v in to_image((c + t.offset_px)[None])[0] - ci]}
        for t, role in drawn]}


def _fmt(t: tuple[float, float]) -> str:
    return f"[{t[0]:g}, {t[1]:g}]"


def check_target_side(points: np.ndarray, angles_deg: np.ndarray | list[float],
                      centre_px: np.ndarray, holder: HolderConfig,
                      to_image: ToImage = lambda p: p) -> None:
    """HolderFrameError where the configured target lies far from the axis and a turned one
    near it (module docstring); nothing where the target is nearer the holder's centre than
    MIN_TARGET_MM."""
    d = math.hypot(*holder.target_mm)
    if d < MIN_TARGET_MM:
        return
    su, sv = holder.size_mm
    square = abs(su - sv) <= SQUARE_WITHIN * max(su, sv)
    got = candidate_offsets(points, angles_deg, centre_px, holder,
                            (0, 2, 1, 3) if square else (0, 2))
    here, others = got[0], got[1:]
    near = min(others, key=lambda c: c.offset_mm)
    if not (near.offset_mm <= NEAR_FRACTION * d and here.offset_mm >= d):
        return
    how = ("opposite it through the holder's centre" if near.quarter_turns == 2 else
           "a quarter turn from it round the holder's centre")
    why = ("the top camera turned 180 deg from the one the config was written for, or the "
           "holder mounted the other way round" if near.quarter_turns == 2 else
           "the top camera or the square holder turned by 90 deg")
    raise HolderFrameError(
        f"target on the other side: holder.target_mm {_fmt(holder.target_mm)} lies "
        f"{here.offset_mm:.2f} mm from the rotation axis at turntable 0, but the point "
        f"{how}, {_fmt(near.target_mm)}, lies {near.offset_mm:.2f} mm from it: the sample "
        f"is not where holder.target_mm puts it ({why}). Fix: set holder.target_mm: "
        f"{_fmt(near.target_mm)} (check the target on the run's picture; docs/configure.md, "
        "the holder frame); if the sample really is that far from the axis, move it nearer "
        "by hand; no stage was moved on this sweep's data",
        _evidence(centre_px, to_image, [(here, "config"), (near, "fix")]))


def image_frame(holder: HolderConfig, ref: ReferenceOrder) -> HolderConfig:
    """The holder in the image's own frame where the config's u and v are the other way
    round (``ref.swapped``): its lengths in the image's order, the target turned as a
    config whose u pointed right would have it."""
    su, sv = holder.size_mm
    return holder.model_copy(update={"size_mm": (sv, su),
                                     "target_mm": ref.image_target_mm(holder.target_mm)})


def swapped_frame_error(points: np.ndarray, angles_deg: np.ndarray | list[float],
                        centre_px: np.ndarray, holder: HolderConfig, ref: ReferenceOrder,
                        to_image: ToImage = lambda p: p) -> HolderFrameError:
    """The refusal of a config whose u and v are the other way round from the image's,
    naming the target that lies near the swept axis: of the two a symmetric rectangle
    cannot tell apart (turned one way or the other), the sample's side."""
    su, sv = holder.size_mm
    frame = image_frame(holder, ref)
    guess, other = candidate_offsets(points, angles_deg, centre_px, frame, (0, 2))
    d = math.hypot(*holder.target_mm)
    if d >= MIN_TARGET_MM and other.offset_mm <= NEAR_FRACTION * d <= guess.offset_mm:
        guess, other = other, guess
    if d >= MIN_TARGET_MM and guess.offset_mm <= NEAR_FRACTION * d:
        which = (f"the point the sample is at: it lies {guess.offset_mm:.2f} mm from the "
                 f"rotation axis, {_fmt(other.target_mm)} {other.offset_mm:.2f} mm")
    else:
        which = (f"if your u pointed right in the image; neither it ({guess.offset_mm:.2f} "
                 f"mm) nor {_fmt(other.target_mm)} ({other.offset_mm:.2f} mm) lies near the "
                 "rotation axis: check the target on the run's picture")
    return HolderFrameError(
        f"holder frame swapped: holder.size_mm [{su:g}, {sv:g}] gives u (corner 0 -> 1, "
        f"the top side in the image) the {'longer' if su > sv else 'shorter'} side, but "
        f"in the top image at turntable 0 u measures {ref.u_px:.0f} px and v "
        f"{ref.v_px:.0f} px: the camera (or the holder) is turned past the holder's "
        f"diagonal. Fix: set holder.size_mm: [{sv:g}, {su:g}] and holder.target_mm: "
        f"{_fmt(guess.target_mm)} ({which}; docs/configure.md, the holder frame), or run "
        "`alignctl commission`; no stage was moved on this sweep's data",
        _evidence(centre_px, to_image, [(guess, "fix"), (other, "other")]))
