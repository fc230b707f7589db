"""``alignctl analyze top|side|rim|camera IMAGE...``: measure camera frames offline.

- ``top``: the holder's corners and pose (centre, angle) and a quality figure per image;
  with ``--sweep-out FILE`` the series becomes a sweep file for ``alignctl solve`` (angles
  from ``--angles`` or from the file names, e.g. ``sweep_-10.0deg.png``).
- ``side``: the sample-edge angle, the pole angle and the tilt between them.
- ``rim``: the turntable rim's ellipse, its eccentricity and the camera zenith it implies.
- ``camera``: what the camera does to its frames, from frames of one still view (any
  scene with dark and bright parts; 8 frames, as the camera delivers them): clipping, JPEG
  coding, defective pixels, sharpening or smoothing, and its tone curve (gamma), each with
  what to do about it. One result for all the frames.

Each image is analysed on its own: an unreadable image or one without a target is
reported (stderr, and an ``{"file", "error"}`` line with ``--json``), the others are still
analysed, and the exit code is then 2. With ``--mean`` (side, rim) the images are frames of
one still view, measured together as the alignment's pre-check does (the mean of their
noise; JPEG frames' coding bias taken off for the side): one result for all of them, or
one error (exit code 2).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from alignd.errors import InputError, VisionError

if TYPE_CHECKING:
    from alignd.vision.lens import Lens

_ANGLE_RE = re.compile(r"(?<![\d.])([-+]?\d+(?:\.\d+)?)\s*deg", re.IGNORECASE)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``analyze``."""
    p = sub.add_parser("analyze", help="measure top / side / rim camera images offline",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=["top", "side", "rim", "camera"],
                   help="what the images show (camera: frames of one still view, checked "
                        "for what the camera does to them)")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image file(s): PNG, JPEG, TIFF...")
    p.add_argument("--json", action="store_true",
                   help="one JSON object per line per image (the analyze-output contract)")
    p.add_argument("--mean", action="store_true",
                   help="side, rim: the images are frames of one still view; measure them "
                        "together as the pre-check does (one result, u from all frames)")
    g = p.add_argument_group("top")
    g.add_argument("--expected-size", metavar="L,S", type=_pair,
                   help="holder's long and short side in px (rejects other blobs)")
    g.add_argument("--polarity", choices=["dark", "light"],
                   help="holder darker or lighter than its surroundings (default: either)")
    g.add_argument("--sweep-out", metavar="FILE", help="write the series as a sweep file")
    g.add_argument("--turntable-deg", type=float, default=None,
                   help="turntable angle for the sample yaw (default: from the file name, else 0)")
    g.add_argument("--angles", metavar="A,B,...", type=_floats,
                   help="turntable angle (deg) of each image, in order (else from file names)")
    g.add_argument("--pixel-size-um", type=float, help="pixel size for the sweep file")
    g.add_argument("--k1", type=float, default=0.0,
                   help="radial distortion (OpenCV k1) of top and rim frames; needs "
                        "--focal-px and --principal")
    g.add_argument("--focal-px", type=float, help="focal length in px (with --k1)")
    g.add_argument("--principal", metavar="X,Y", type=_pair,
                   help="principal point in px (with --k1; default: the image centre)")
    g.add_argument("--holder-mm", metavar="L,S", type=_pair,
                   help="holder's sides in mm; with --pixel-size-um gives --expected-size")
    g = p.add_argument_group("side")
    g.add_argument("--pole-x", type=float, help="approximate x (px) of the reference pole")
    g.add_argument("--sample-x", type=float, help="approximate x (px) of the sample edge")
    g.add_argument("--pole-roi", metavar="X0,Y0,X1,Y1", type=_box,
                   help="region of the pole (px; default: automatic)")
    g.add_argument("--sample-roi", metavar="X0,Y0,X1,Y1", type=_box,
                   help="region of the sample edge (px; default: automatic)")
    p.add_argument("--gamma", type=_tone_curve, default=None,
                   help="the camera's tone curve, undone before measuring (cameras[].gamma: "
                        "1 linear, about 2.2 for UVC cameras, or srgb or bt709; default: the "
                        "config's camera, else 1)")
    p.add_argument("--role", choices=["top", "side"], default="top",
                   help="camera: whose config gamma (with --config) the frames are held "
                        "against (default top)")
    p.add_argument("--config", metavar="FILE",
                   help="take the holder size, the top camera's pixel size, gamma and "
                        "lens, and the side camera's regions and gamma from an alignd config "
                        "(options given win)")
    g = p.add_argument_group("rim")
    g.add_argument("--radius-mm", type=float, default=150.0, help="rim radius (default 150)")
    g.add_argument("--height-mm", type=float, default=800.0,
                   help="camera height above the turntable (default 800)")
    p.set_defaults(func=run)


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers 'L,S', got {text!r}") from None
    return a, b


def _box(text: str) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected four integers 'X0,Y0,X1,Y1', got {text!r}"
                                         ) from None
    if not (0 <= x0 < x1 and 0 <= y0 < y1):
        raise argparse.ArgumentTypeError(f"region {text!r}: need 0 <= X0 < X1, 0 <= Y0 < Y1")
    return x0, y0, x1, y1


def _apply_config(args: argparse.Namespace) -> None:
    """Fill unset options from ``--config`` (holder size, pixel size, side regions, the
    camera's gamma, the top camera's lens)."""
    if args.config:
        from alignd.config import load_config
        from alignd.procedures.tools import expected_holder_px
        cfg = load_config(args.config)
        if args.expected_size is None and args.holder_mm is None:
            args.expected_size = expected_holder_px(cfg)
        if args.pixel_size_um is None:
            cam = cfg.camera("top")
            args.pixel_size_um = cam.pixel_size_um if cam is not None else None
        args.pole_roi = args.pole_roi or cfg.side_camera.pole_roi_px
        args.sample_roi = args.sample_roi or cfg.side_camera.sample_roi_px
        seen_by = cfg.camera("side" if args.kind == "side" else "top")
        if args.gamma is None and seen_by is not None:
            args.gamma = seen_by.gamma
        top = cfg.camera("top")
        if not args.k1 and top is not None and top.lens is not None:  # cameras[].lens
            args.k1, args.focal_px = top.lens.k1, top.lens.focal_px
            args.principal = args.principal or top.lens.principal_px
    if isinstance(args.gamma, float) and not (math.isfinite(args.gamma)
                                              and 1.0 <= args.gamma <= 3.0):
        raise InputError(f"--gamma {args.gamma:g}: the camera's tone curve is within 1-3 (1: "
                         "linear), or srgb or bt709")
    if args.holder_mm is not None and args.expected_size is None:
        if args.pixel_size_um is None:
            raise InputError("--holder-mm needs --pixel-size-um (or --config)")
        a, b = args.holder_mm
        args.expected_size = (max(a, b) * 1000 / args.pixel_size_um,
                              min(a, b) * 1000 / args.pixel_size_um)


def _tone_curve(text: str) -> float | str:
    """--gamma: a number, or a named curve (drivers.tone_curves)."""
    if text.lower() in ("srgb", "bt709"):
        return text.lower()
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a number (1-3) or srgb or bt709"
                                         ) from None


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}"
                                         ) from None


def read_image(name: str) -> np.ndarray:
    """Grey image as float-compatible uint8 (16-bit scaled); InputError if unreadable."""
    if not Path(name).is_file():
        raise InputError(f"{name}: no such image file")
    img = cv2.imread(name, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"{name}: cannot read image (not an image format OpenCV decodes)")
    if img.ndim == 3:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY)
    if img.dtype not in (np.uint8, np.uint16):  # 16-bit: the vision scales by bit depth
        img = img.astype(np.float32)
    return img


def _linear(img: np.ndarray, args: argparse.Namespace) -> np.ndarray:
    """``img`` with the camera's tone curve (``--gamma``) undone."""
    from alignd.vision import linearise
    return linearise(img, args.gamma if args.gamma is not None else 1.0)


def _angle_from_name(name: str) -> float | None:
    m = _ANGLE_RE.findall(Path(name).stem)
    return float(m[-1]) if m else None


def _fmt(v: float, nd: int = 3) -> str:
    return f"{v:.{nd}f}" if math.isfinite(v) else "nan"


def _lens(args: argparse.Namespace, shape: tuple[int, ...]) -> Lens | None:
    """The top camera's lens from ``--k1`` (and ``--focal-px``, ``--principal``, or the
    config's ``cameras[].lens``); None without one."""
    from alignd.vision.lens import Lens

    if not args.k1:
        return None
    if args.focal_px is None:
        raise InputError("--k1 needs --focal-px")
    pp = args.principal or ((shape[1] - 1) / 2, (shape[0] - 1) / 2)
    return Lens(args.focal_px, pp, args.k1)


def _analyze_one(kind: str, name: str, args: argparse.Namespace,
                 prev: np.ndarray | None) -> tuple[dict[str, object], str, np.ndarray | None]:
    """JSON object, human line, and (top) the corners for the sweep; raises on failure."""
    img = _linear(read_image(name), args)
    lens = _lens(args, img.shape)
    if kind == "top":
        from alignd.vision.holder import measure_yaw, order_corners, track_holder
        det = track_holder(img, expected_size_px=args.expected_size, polarity=args.polarity,
                           lens=lens, hint=prev)
        if not det.ok:
            raise VisionError(f"holder not measured: {det.reason or 'quality checks failed'}")
        corners = order_corners(det.corners_px, prev) if prev is not None else det.corners_px
        obj = det.to_json()
        obj["corners_px"] = [[float(x), float(y)] for x, y in corners]
        turn = args.turntable_deg if args.turntable_deg is not None else (
            _angle_from_name(name) or 0.0)
        yaw = measure_yaw(img, det, turntable_deg=turn)
        obj["sample_yaw_deg"] = yaw.yaw_deg if yaw.ok else None
        line = (f"centre ({_fmt(det.center_px[0])}, {_fmt(det.center_px[1])}) px  angle "
                f"{det.angle_deg:+.4f} deg  quality {det.quality:.3f}  corner sigma "
                f"{det.corner_sigma_px:.4f} px  sample yaw "
                + (f"{yaw.yaw_deg:+.4f} deg" if yaw.ok else f"- ({yaw.reason})")
                + "  corners " + " ".join(f"({x:.3f}, {y:.3f})" for x, y in corners)
                + (f"\n  warning: {det.warning}" if det.warning else ""))
        return obj, line, corners
    if kind == "side":
        from alignd.vision.side import measure_tilt
        m = measure_tilt(img, pole_x_px=args.pole_x, sample_x_px=args.sample_x,
                         pole_roi_px=args.pole_roi, sample_roi_px=args.sample_roi)
        line = (f"sample {m.sample_angle_deg:+.4f} deg  pole {m.pole_angle_deg:+.4f} deg  "
                f"tilt {m.tilt_deg:+.4f} +- {m.sigma_deg:.4f} deg")
        return m.to_json(), line, None
    from alignd.vision.rim import fit_rim
    f = fit_rim(img, args.radius_mm, args.height_mm, lens=lens)
    line = (f"ellipse centre ({f.center_px[0]:.3f}, {f.center_px[1]:.3f}) px  axes "
            f"{f.axes_px[0]:.3f} x {f.axes_px[1]:.3f} px  angle {f.angle_deg:+.2f} deg  "
            f"e {f.eccentricity:.4f}  camera zenith {_fmt(f.camera_zenith_deg, 3)} deg")
    return f.to_json(), line, None


def _analyze_mean(kind: str, names: list[str], args: argparse.Namespace
                  ) -> tuple[dict[str, object], str]:
    """One measurement from all the frames (``--mean``): JSON object and human line."""
    images = [read_image(n) for n in names]
    if any(img.shape != images[0].shape for img in images):
        raise InputError("--mean: the frames differ in size (not one camera's view)")
    if kind == "side":  # the frames as coded (the JPEG bias step reads it), gamma undone inside
        from alignd.vision.side import measure_tilt_frames
        t = measure_tilt_frames(images, pole_roi_px=args.pole_roi, sample_roi_px=args.sample_roi,
                                gamma=args.gamma if args.gamma is not None else 1.0)
        obj = t.to_json()
        line = (f"sample {obj['sample_angle_deg']:+.4f} deg  pole {obj['pole_angle_deg']:+.4f} "
                f"deg  tilt {t.tilt_deg:+.4f} +- {t.u_deg:.4f} deg")
        return obj, line
    from alignd.vision.rim import fit_rim_frames
    f = fit_rim_frames([_linear(img, args) for img in images], args.radius_mm, args.height_mm,
                       lens=_lens(args, images[0].shape))
    line = (f"ellipse centre ({f.center_px[0]:.3f}, {f.center_px[1]:.3f}) px  axes "
            f"{f.axes_px[0]:.3f} x {f.axes_px[1]:.3f} px  e {f.eccentricity:.4f} +- "
            f"{_fmt(f.eccentricity_std, 4)}  camera zenith {_fmt(f.camera_zenith_deg, 3)} deg")
    return {**f.to_json(), "frames": len(images)}, line


def run(args: argparse.Namespace) -> int:
    from alignd.cli import EXIT_OK, EXIT_USAGE

    if args.kind != "top" and (args.sweep_out or args.angles):
        raise InputError("--sweep-out/--angles apply to 'analyze top' only")
    if args.mean and args.kind == "top":
        raise InputError("--mean applies to 'analyze side' and 'analyze rim' (a top sweep's "
                         "frames are at different angles: --sweep-out)")
    if args.kind == "camera":
        return _check_camera(list(args.images), args.json, args.config, args.role)
    _apply_config(args)
    if args.mean:
        try:
            obj, line = _analyze_mean(args.kind, list(args.images), args)
        except (InputError, VisionError) as exc:
            print(f"alignctl analyze: error: {exc}", file=sys.stderr)
            if args.json:
                print(json.dumps({"files": list(args.images), "error": str(exc)}), flush=True)
            return EXIT_USAGE
        if args.json:
            print(json.dumps({"files": list(args.images), **obj}), flush=True)
        else:
            print(f"mean of {len(args.images)} frames: {line}", flush=True)
        return EXIT_OK
    angles: list[float] | None = None
    if args.sweep_out:
        if args.angles is not None:
            if len(args.angles) != len(args.images):
                raise InputError(f"--angles has {len(args.angles)} values for "
                                 f"{len(args.images)} images")
            angles = list(args.angles)
        else:
            found = [_angle_from_name(n) for n in args.images]
            missing = [n for n, a in zip(args.images, found, strict=True) if a is None]
            if missing:
                raise InputError(f"no turntable angle for {missing[0]} (name it like "
                                 "'frame_-10.0deg.png' or give --angles)")
            angles = [float(a) for a in found if a is not None]
    status = EXIT_OK
    prev: np.ndarray | None = None
    features: list[np.ndarray] = []
    for name in args.images:
        try:
            obj, line, corners = _analyze_one(args.kind, name, args, prev)
        except (InputError, VisionError) as exc:
            msg = str(exc) if str(exc).startswith(name) else f"{name}: {exc}"
            print(f"alignctl analyze: error: {msg}", file=sys.stderr)
            if args.json:
                print(json.dumps({"file": name, "error": msg}), flush=True)
            status = EXIT_USAGE
            features.append(np.full((4, 2), np.nan))
            continue
        if corners is not None:
            prev = corners
            features.append(np.asarray(corners, float))
        if args.json:
            print(json.dumps({"file": name, **obj}), flush=True)
        else:
            print(f"{name}: {line}", flush=True)
    if args.sweep_out and angles is not None:
        _write_sweep(args.sweep_out, angles, features, args.pixel_size_um)
    return status


def _check_camera(names: list[str], as_json: bool, config: str | None, role: str) -> int:
    """``analyze camera``: one check of all the frames (vision.camera_check); with a
    config, its ``role`` camera's gamma held against what the frames allow."""
    from alignd.cli import EXIT_OK, EXIT_USAGE
    from alignd.vision.camera_check import Finding, check_frames, gamma_text
    from drivers.tone_curves import curve_text, disagrees
    try:
        c = check_frames([read_image(n) for n in names])
        if config:
            from alignd.config import load_config
            cam = load_config(config).camera(role)
            configured = cam.gamma if cam is not None else 1.0
            if math.isfinite(c.gamma) and disagrees(configured, c.gamma_range):
                said = Finding("config_gamma", "act", f"{config} says "
                               f"{curve_text(configured)} for the {role} camera, its frames "
                               f"{gamma_text(c)}", f"set cameras[{role}].gamma (measure it "
                               "with two exposures, docs/configure.md)")
                c = dataclasses.replace(c, findings=[said, *c.findings])
    except (InputError, VisionError) as exc:
        print(f"alignctl analyze: error: {exc}", file=sys.stderr)
        if as_json:
            print(json.dumps({"files": names, "error": str(exc)}), flush=True)
        return EXIT_USAGE
    if as_json:
        print(json.dumps({"files": names, **c.to_json()}), flush=True)
        return EXIT_OK
    corr = " / ".join(_fmt(v, 2) for v in c.noise_correlation)
    print(f"{c.frames} frame(s) of {c.size_px[0]} x {c.size_px[1]} px, {c.bits}-bit; "
          f"clipped {100 * c.clipped_high:.2f} % at full scale, {100 * c.clipped_low:.2f} % "
          f"at zero; JPEG quality {c.jpeg_quality or '-'}; noise {_fmt(c.noise_dn, 2)} DN, "
          f"neighbours' correlation {corr} (rows / columns); {gamma_text(c)}", flush=True)
    for f in c.findings:
        print(f"  [{f.level}] {f.what}" + (f": {f.advice}" if f.advice else ""), flush=True)
    return EXIT_OK


def _write_sweep(path: str, angles: list[float], features: list[np.ndarray],
                 pixel_size_um: float | None) -> None:
    """The sweep-file contract (version 1); a missed image's corners are null."""
    pts = np.asarray(features, float).reshape(len(features), 4, 2)
    if not np.isfinite(pts).any():
        raise InputError(f"{path}: not written, the holder was found in no image")
    try:
        from alignd.solve.sweep import Sweep, sweep_to_json
        obj = sweep_to_json(Sweep(angles_deg=np.asarray(angles, float), points=pts,
                                  pixel_size_um=pixel_size_um))
    except ImportError:  # the solver package is optional for this command
        obj = {"version": 1, "pixel_size_um": pixel_size_um,
               "frames": [{"angle_deg": float(a), "features": [
                   [float(p[0]), float(p[1])] if np.all(np.isfinite(p)) else None for p in fr]}
                   for a, fr in zip(angles, pts, strict=True)]}
    try:
        Path(path).write_text(json.dumps(obj, indent=1) + "\n", encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{path}: cannot write sweep file: {exc.strerror or exc}") from exc
