"""The continuous (on-the-fly) sweep: turn at constant speed while the top camera streams.

Stop-and-go spends most of a sweep accelerating, settling and waiting for one frame per
step. Here the turntable runs from ``-half`` to ``+half`` (in its approach direction, after
a verified move to the start that takes the backlash out) at the speed
``config.continuous_speed`` allows for the camera's exposure, and every frame the camera
delivers is tracked: many more frames per second of motion. A frame's turntable angle
comes from the images (the ``rigid`` fit estimates each frame's angle jointly with the
centre); the read-back, sampled around every frame and interpolated at the frame's
mid-exposure time, is the prior that starts that fit and fixes its common zero. So frames
taken while the stage accelerates are as good as the others, and a camera timestamp a few
milliseconds off costs nothing. Frames are tracked after the turn, so tracking never
slows the stream.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Literal

import numpy as np

from alignd.config import AligndConfig, continuous_speed
from alignd.errors import SolveError
from alignd.procedures.events import ProgressCallback, ProgressEvent
from alignd.procedures.recorder import RunRecorder
from alignd.procedures.rig import Rig, check_abort
from alignd.procedures.tools import Tools
from drivers.camera import Frame

if TYPE_CHECKING:
    from alignd.procedures.sweep import SweepData

log = logging.getLogger(__name__)

MAX_FRAMES = 5000  # a stream that never reaches the end (a stage that stopped short) ends


def run_continuous_sweep(rig: Rig, cfg: AligndConfig, tools: Tools, *, kind: str,
                         iteration: int, abort: threading.Event | None,
                         progress: ProgressCallback, recorder: RunRecorder, half_deg: float,
                         frames_per_step: int = 1,
                         approach: Literal["+", "-"] | None = None) -> SweepData:
    """Turn from ``-half_deg`` to ``+half_deg`` at constant speed, tracking every frame.

    Returns the same ``SweepData`` as the step sweep: ``readback_deg`` holds each frame's
    read-back interpolated at its mid-exposure time (the prior; ``measure`` replaces it by
    the image angles), ``commanded_deg`` the same (nothing is commanded per frame).
    ``frames_per_step`` > 1 turns that many times slower (more frames per degree);
    ``approach`` turns it in that direction (default: the turntable's approach).
    """
    from alignd.procedures.sweep import SweepData

    tt = rig.axis("turntable")
    cam = rig.camera("top")
    assert cam is not None  # validate_rig guarantees it
    c = cfg.procedure.continuous
    speed, blur = continuous_speed(cfg, frames_per_step)
    # frames come at the camera's rate of simulated time: a time-scaled simulator (its
    # axes' time_scale) runs the turn, and so the stream, that many times faster
    period = 1.0 / c.frame_rate_hz / max(tt.config.time_scale, 1e-9)
    sign = 1.0 if (approach or tt.config.approach) == "+" else -1.0
    # a lead-in of the acceleration distance each side, inside the soft limits
    lead = min(speed**2 / (2 * tt.config.accel), 1.0) if tt.config.accel > 0 else 0.0
    lo, hi = tt.config.soft_limits.min, tt.config.soft_limits.max
    start = min(max(-sign * (half_deg + lead), lo), hi)
    end = min(max(sign * (half_deg + lead), lo), hi)
    clock = tt.clock
    t0 = time.perf_counter()
    check_abort(abort)
    if approach is None:
        tt.move_to(start)
    else:
        tt.move_to(start, approach)
    t_motion = time.perf_counter() - t0
    log.info("%s sweep %d: continuous %+.2f -> %+.2f deg at %.3g deg/s, %g fps, blur %.2f px",
             kind, iteration, start, end, speed, c.frame_rate_hz, blur)
    frames: list[Frame] = []
    points: list[np.ndarray] = []
    stamps: list[float] = []
    hashes: list[str] = []
    samples_t: list[float] = []
    samples_a: list[float] = []
    t_track = t_grab = 0.0
    n_expected = max(int(abs(end - start) / speed * c.frame_rate_hz), 1)
    with tt.speed_limited(speed):
        here = tt.position()
        samples_t.append(clock.now())
        samples_a.append(here)
        tt.start_move(end)
        t_begin = clock.now()
        # a stage that stops short ends the stream; end_move then says why
        give_up = t_begin + (2.0 * abs(end - here) / speed + 2.0) / max(tt.config.time_scale,
                                                                        1e-9)
        last_ts: float | None = None
        try:
            for k in range(MAX_FRAMES):
                check_abort(abort)
                wait = t_begin + (k + 1) * period - clock.now()
                if wait > 0:
                    clock.sleep(wait)
                t1 = time.perf_counter()
                frame = cam.grab(after=last_ts)
                t_grab += time.perf_counter() - t1
                samples_t.append(clock.now())
                pos = tt.position()
                samples_a.append(pos)
                last_ts = frame.timestamp
                frames.append(frame)  # tracked after the turn: the stream is not slowed
                if k % 10 == 0:
                    progress(ProgressEvent("sweep" if kind != "verify" else "verify",
                                           f"{kind} sweep (continuous) at {pos:+.3f} deg",
                                           step=min(k + 1, n_expected), total=n_expected,
                                           iteration=iteration))
                if abs(pos - end) <= tt.config.deadband or clock.now() > give_up:
                    break
            t4 = time.perf_counter()
            tt.end_move(end, here)
            t_motion += time.perf_counter() - t4
        except BaseException:
            tt.stop()  # never leave the table turning (and its speed can then be restored)
            raise
    warned, warning = 0, ""
    for k, frame in enumerate(frames):
        check_abort(abort)
        t2 = time.perf_counter()
        det = tools.track(frame)
        t_track += time.perf_counter() - t2
        hashes.append(recorder.frame(frame.image, f"{kind}-{iteration}-{k:03d}-0"))
        stamps.append(frame.timestamp)
        points.append(det.corners_px if det.ok else np.full((4, 2), np.nan))
        if det.ok and det.warning:
            warned += 1
            warning = warning or det.warning
    prior = np.interp(stamps, samples_t, samples_a)
    log.info("%s sweep %d: %d frames over %.2f deg", kind, iteration, len(points),
             abs(end - start))
    return SweepData(kind, iteration, prior.tolist(), prior.tolist(),
                     np.array(points, float).reshape(-1, 4, 2), hashes, track_s=t_track,
                     grab_s=t_grab, motion_s=t_motion, mode="continuous",
                     warned_frames=warned, warning=warning)


def frame_angles(angles_deg: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Each frame's angle from the images: the ``rigid`` fit's angles, started at (and
    with its common zero matched to) the prior ``angles_deg``; a frame the fit did not
    use keeps its prior."""
    from alignd.solve import Sweep, solve_centre

    prior = np.asarray(angles_deg, float)
    try:
        res = solve_centre(Sweep(prior, np.asarray(points, float), None), method="rigid")
    except (SolveError, ValueError, np.linalg.LinAlgError) as exc:
        log.warning("frame angles from the images failed (%s); using the read-back", exc)
        return prior
    est = np.asarray(res.angles_deg, float)
    if est.shape != prior.shape:
        return prior
    return np.where(np.isfinite(est), est, prior)
