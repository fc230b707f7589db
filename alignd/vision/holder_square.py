"""The holder's four sides sharing one direction where they agree with a rectangle.

Each side is fitted as a free line: a camera that looks a little obliquely through a lens
with perspective sees the rectangle as a general quadrilateral (a keystone), and a fit
that forced a rectangle on it would move its corners. But a corner is the end of two
fitted lines, and at a line's end three quarters of the variance comes from its direction
(the offset's variance, plus three times as much from the slope's over half the line's
length). Where the four directions agree with a rectangle's (one direction modulo 90 deg)
within their standard errors, they share it: each side takes the inverse-variance mean of
the four and its offset is fitted again through its own crossings. Where they do not and
only an opposite pair agrees (a side parallel to the tilt axis stays parallel to its
opposite), that pair shares its direction. A camera square to the turntable, or a
telecentric lens, sees the rectangle; a tilted one shows a keystone and the free sides
stand, and a keystone within the test's reach (about 1-2 standard errors of a side's
direction) is the price (docs/vision.md, "A holder seen square").
"""

from __future__ import annotations

import math

from alignd.vision.edges import EdgePoints, Line, fit_line

__all__ = ["parallel_to", "square_sides"]

# four directions agree with a rectangle when the chi-square of their deviations from
# their mean (3 degrees of freedom) is under this (p about 0.7 %); an opposite pair when
# its difference is under _PAIR_Z standard errors. Measured on the corpus and on holders
# seen by a tilted camera (docs/vision.md): stricter tests pool too rarely to gain, looser
# ones pool a keystone
_RECT_CHI2 = 12.0
_PAIR_Z = 2.0


def _slope(ln: Line) -> float:
    """b of the line's minor = a + b * major."""
    n0, n1 = float(ln.n[0]), float(ln.n[1])
    return -n1 / n0 if ln.vertical else -n0 / n1


def _direction(ln: Line) -> tuple[float, float]:
    """The line's direction (rad, x toward y, modulo pi) and its variance."""
    b = _slope(ln)
    return math.radians(ln.angle_deg), float(ln.cov_ab[1, 1]) / (1.0 + b * b) ** 2


def _wrap(x: float, period: float) -> float:
    return (x + period / 2) % period - period / 2


def _refit(ln: Line, pts: EdgePoints, phi: float, var: float) -> Line:
    """The side fitted again through its crossings with the direction ``phi`` (its
    variance ``var``) given."""
    if ln.vertical:
        s, c = math.sin(phi), math.cos(phi)
        b = c / s if abs(s) > 1e-9 else _slope(ln)
    else:
        b = math.tan(phi)
    again = fit_line(pts, slope=(b, var * (1.0 + b * b) ** 2))
    return again if again is not None else ln


def square_sides(lines: list[Line | None], points: list[EdgePoints]) -> list[Line | None]:
    """The four sides (corner k to corner k + 1, in the ideal image; ``points``: the
    crossings each was fitted to) with their directions pooled where they agree with a
    rectangle's, or an opposite pair's with each other (see the module docstring)."""
    if len(lines) != 4 or any(ln is None for ln in lines):
        return lines
    sides = [ln for ln in lines if ln is not None]
    dirs = [_direction(ln) for ln in sides]
    if not all(v > 0.0 and math.isfinite(v) for _phi, v in dirs):
        return lines
    ref = dirs[0][0]
    dev = [_wrap(phi - ref, math.pi / 2) for phi, _v in dirs]
    w = [1.0 / v for _phi, v in dirs]
    mean = sum(wi * di for wi, di in zip(w, dev, strict=True)) / sum(w)
    chi2 = sum(wi * (di - mean) ** 2 for wi, di in zip(w, dev, strict=True))
    if chi2 < _RECT_CHI2:
        var = 1.0 / sum(w)
        return [_refit(ln, pts, phi - di + mean, var) for ln, pts, (phi, _v), di
                in zip(sides, points, dirs, dev, strict=True)]
    out: list[Line | None] = list(sides)
    for k in (0, 1):
        (p0, v0), (p2, v2) = dirs[k], dirs[k + 2]
        d = _wrap(p2 - p0, math.pi)
        if d * d < _PAIR_Z ** 2 * (v0 + v2):
            phi, var = p0 + d * v0 / (v0 + v2), v0 * v2 / (v0 + v2)
            out[k] = _refit(sides[k], points[k], phi, var)
            out[k + 2] = _refit(sides[k + 2], points[k + 2], phi, var)
    return out


def parallel_to(ln: Line, pts: EdgePoints, other: Line) -> Line:
    """``ln``, or where its direction disagrees with ``other``'s (its opposite side) by
    more than _PAIR_Z standard errors, ``ln`` fitted again through ``pts`` with
    ``other``'s direction and its variance: for a side whose crossings show beside one end
    only, where a few stray crossings by whatever hides the rest can set its direction
    (their residuals then small, its stated variance too)."""
    (p0, v0), (p1, v1) = _direction(ln), _direction(other)
    d = _wrap(p1 - p0, math.pi)
    if d * d <= _PAIR_Z ** 2 * (v0 + v1):
        return ln
    return _refit(ln, pts, p1, v1)
