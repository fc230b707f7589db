"""alignd's vision: pure functions from camera frames to measurements (no I/O, no state).

- :func:`track_holder` (top camera): holder corners, pose and quality per frame;
  :func:`measure_yaw`: the sample face's yaw from the turntable zero direction.
- :func:`measure_tilt` (side camera): sample and pole angles and the tilt between them;
  :func:`measure_tilt_frames`: the mean of several frames and its uncertainty (the
  pre-check); :func:`baseline_tilt`: the thesis' Canny + Hough method, for comparison.
- :func:`fit_rim`: turntable rim ellipse, eccentricity and camera zenith (eq. 3.7);
  :func:`fit_rim_frames`: the same on the mean of several frames (the pre-check);
  :class:`PlaneRectifier`: image points rectified to the turntable plane.
- :func:`linearise`: a camera's tone curve (its config's ``gamma``) undone, before any of
  the above.
- :mod:`alignd.vision.overlay`: report drawings.
"""

from alignd.vision.edges import linearise
from alignd.vision.holder import (
    HolderDetection,
    YawMeasurement,
    measure_yaw,
    order_corners,
    track_holder,
)
from alignd.vision.lens import Lens
from alignd.vision.rim import (
    PlaneRectifier,
    RimFit,
    camera_zenith_from_eccentricity,
    eccentricity_from_zenith,
    fit_rim,
    fit_rim_frames,
    zenith_from_ellipse,
)
from alignd.vision.side import (
    SideMeasurement,
    TiltAverage,
    baseline_tilt,
    measure_tilt,
    measure_tilt_frames,
)

__all__ = [
    "HolderDetection",
    "Lens",
    "PlaneRectifier",
    "RimFit",
    "SideMeasurement",
    "TiltAverage",
    "YawMeasurement",
    "baseline_tilt",
    "camera_zenith_from_eccentricity",
    "eccentricity_from_zenith",
    "fit_rim",
    "fit_rim_frames",
    "linearise",
    "measure_tilt",
    "measure_tilt_frames",
    "measure_yaw",
    "order_corners",
    "track_holder",
    "zenith_from_ellipse",
]
