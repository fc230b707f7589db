"""Rigid-body fit: every tracked feature turns with the holder about one common centre.

Model, per frame f and feature k (y-down pixel coordinates)::

    p_fk = c + R(a_f) (q_k - c) + noise,     q_k: feature k at angle 0

With the angles known (turntable readback, ``rigid-known``) the model is linear in
(c, q) and one weighted least-squares solve gives the answer. With the angles free
(``rigid``) they are estimated jointly from the images, the readback serving only as the
starting point, so a turntable's backlash or encoder error does not bias the centre. The
angle offset common to all frames is a gauge freedom (it rotates the q_k about c and leaves c
alone); it is fixed by holding one frame's angle during the fit and afterwards by matching
the mean estimated angle to the mean readback.

Robustness: Huber IRLS (scale from the median residual) to get near the answer despite
gross tracking errors, then hard rejection at the chi-square 99.9 % point with the scale
re-estimated from the inliers, refitting until the inlier set is stable. The covariance
is sigma^2 (J'J)^-1 for the centre, the angles marginalised (Schur complement), with sigma^2
estimated from the inlier residuals with their degrees of freedom, so it needs no prior
knowledge of the detection noise. With the angles free, two terms keep it honest where
the features' errors are not independent: sigma is at least the scale of the frames' mean
residual (``_translation_sigma``: corners found on shared sides err together), and what
the features' own centres disagree by beyond their noise (a texture or a shadow under one
corner's path) is added (``_features_excess``). With independent noise the first is sigma
itself, give or take its scatter, and the second adds nothing 19 times in 20.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.stats import chi2 as chi2_dist

from alignd.errors import SolveError

from .common import (
    CUT_2D,
    MIN_SPREAD_DEG,
    SolveInputs,
    huber_weights,
    paule_mandel,
    robust_sigma_2d,
    weighted_mean,
)
from .result import CentreResult

log = logging.getLogger(__name__)

__all__ = ["fit_rigid", "image_angles"]

_MAX_HUBER = 40
_MAX_MASK = 8
_MAX_GN = 12
EXCESS_LEVEL = 0.95  # the features' centres disagree beyond their noise


class _State:
    """Parameters in the shifted frame (origin at the data centroid)."""

    __slots__ = ("a", "c", "q")

    def __init__(self, c: np.ndarray, q: np.ndarray, a: np.ndarray) -> None:
        self.c, self.q, self.a = c, q, a


def _normal_globals(rx: np.ndarray, ry: np.ndarray, w: np.ndarray, cs: np.ndarray,
                    sn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H_gg and J'W r for the globals (c, q_1..q_K); ``rx, ry`` already weighted.

    The model is linear in the globals: p = (I - R) c + R q, so with r = p the same
    call gives the right-hand side of the direct solve. A feature without weight gets a
    unit diagonal (its q stays put and the centre block is unaffected).
    """
    K = w.shape[1]
    n = 2 + 2 * K
    H = np.zeros((n, n))
    Wf = w.sum(axis=1)
    H[0, 0] = H[1, 1] = (2.0 - 2.0 * cs) @ Wf
    m1 = (cs - 1.0) @ w  # (K,)
    m2 = sn @ w
    wk = w.sum(axis=0)
    H[0, 2::2] = H[2::2, 0] = m1
    H[0, 3::2] = H[3::2, 0] = -m2
    H[1, 2::2] = H[2::2, 1] = m2
    H[1, 3::2] = H[3::2, 1] = m1
    dk = np.where(wk > 0, wk, 1.0)
    H[range(2, n, 2), range(2, n, 2)] = dk
    H[range(3, n, 2), range(3, n, 2)] = dk
    # R^T r
    rtx = cs[:, None] * rx + sn[:, None] * ry
    rty = cs[:, None] * ry - sn[:, None] * rx
    g = np.empty(n)
    sx, sy = rtx.sum(axis=0), rty.sum(axis=0)
    g[0] = rx.sum() - sx.sum()
    g[1] = ry.sum() - sy.sum()
    g[2::2] = sx
    g[3::2] = sy
    return H, g


def _solve_known(Px: np.ndarray, Py: np.ndarray, w: np.ndarray, a: np.ndarray,
                 st: _State) -> np.ndarray:
    """Weighted LS for (c, q) at fixed angles; updates ``st``; returns the normal matrix."""
    H, g = _normal_globals(Px * w, Py * w, w, np.cos(a), np.sin(a))
    try:
        x = np.linalg.solve(H, g)
    except np.linalg.LinAlgError as exc:
        raise SolveError("centre not determined: singular normal equations (no angular spread "
                         "or too few detections)") from exc
    keep = w.sum(axis=0) <= 0
    q = x[2:].reshape(-1, 2)
    q[keep] = st.q[keep]
    st.c, st.q, st.a = x[:2].copy(), q, a
    return H


def _residuals(Px: np.ndarray, Py: np.ndarray, st: _State) -> tuple[np.ndarray, np.ndarray]:
    cs, sn = np.cos(st.a)[:, None], np.sin(st.a)[:, None]
    dx, dy = st.q[:, 0] - st.c[0], st.q[:, 1] - st.c[1]
    return (Px - (cs * dx - sn * dy) - st.c[0], Py - (sn * dx + cs * dy) - st.c[1])


def _gn_free(Px: np.ndarray, Py: np.ndarray, w: np.ndarray, st: _State,
             r: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, float]:
    """One Gauss-Newton step on (c, q, a), the best-seen frame's angle held (gauge).

    Angles are eliminated by their (diagonal) Schur complement. Returns the reduced normal
    matrix of the globals (its inverse is the marginal covariance up to sigma^2) and the
    length of the centre's step. ``r``: the residuals at ``st`` if already computed.
    """
    cs, sn = np.cos(st.a), np.sin(st.a)
    rx, ry = _residuals(Px, Py, st) if r is None else r
    rx, ry = rx * w, ry * w
    H, g = _normal_globals(rx, ry, w, cs, sn)
    dx, dy = st.q[:, 0] - st.c[0], st.q[:, 1] - st.c[1]
    jdx, jdy = -dy, dx  # J d
    # t_fk = R_f J d_k, the derivative of the prediction by a_f
    tx = cs[:, None] * jdx - sn[:, None] * jdy
    ty = sn[:, None] * jdx + cs[:, None] * jdy
    wf = w.sum(axis=1)
    act = wf > 0
    act[int(np.argmax(wf))] = False
    wa = w * act[:, None]
    Haa = np.where(act, w @ (dx * dx + dy * dy), 1.0)
    ga = np.sum(tx * rx + ty * ry, axis=1) * act
    Hga = np.empty((H.shape[0], w.shape[0]))
    Hga[0] = np.sum(wa * (tx - jdx), axis=1)
    Hga[1] = np.sum(wa * (ty - jdy), axis=1)
    Hga[2::2] = (wa * jdx).T
    Hga[3::2] = (wa * jdy).T
    Hs = Hga / Haa
    S = H - Hs @ Hga.T
    try:
        dg = np.linalg.solve(S, g - Hs @ ga)
    except np.linalg.LinAlgError as exc:
        raise SolveError("centre not determined: singular normal equations (no angular spread, "
                         "or the features do not constrain the angles)") from exc
    da = (ga - Hga.T @ dg) / Haa
    st.c = st.c + dg[:2]
    st.q = st.q + dg[2:].reshape(-1, 2)
    st.a = st.a + da * act
    return S, float(np.hypot(dg[0], dg[1]))


def image_angles(P: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Frame angles (rad, mean zero) from the directions between feature pairs alone.

    Median polish of theta_fkl = a_f + phi_kl over frames and pairs: the starting point for
    a sweep without usable readback. NaN for frames with no pair of detections.
    """
    F, K = valid.shape
    thetas = []
    for k in range(K):
        for m in range(k + 1, K):
            both = valid[:, k] & valid[:, m]
            if np.count_nonzero(both) < 2:
                continue
            dv = P[:, m] - P[:, k]
            th = np.where(both, np.arctan2(dv[:, 1], dv[:, 0]), np.nan)
            ref = th[np.flatnonzero(both)[0]]
            thetas.append(np.angle(np.exp(1j * (th - ref))))
    if not thetas:
        raise SolveError("cannot estimate angles from the images: no two features are seen "
                         "together in two frames, and the readback has no spread")
    T = np.stack(thetas, axis=1)  # (F, pairs)
    a = np.zeros(F)
    for _ in range(6):
        phi = np.nanmedian(T - a[:, None], axis=0)
        with np.errstate(all="ignore"):
            a = np.nanmedian(T - phi[None, :], axis=1) if T.size else a
        a = np.where(np.isfinite(a), a, 0.0)
    has = np.isfinite(T).any(axis=1)
    a = np.where(has, a - np.mean(a[has]), np.nan)
    return a


def _pair_start(Px: np.ndarray, Py: np.ndarray, valid: np.ndarray, a: np.ndarray,
                st: _State) -> None:
    """High-breakdown starting point: every detection pair of a feature, one from each end
    of the sweep, fixes the centre given the angles (p_g - p_f = (R_g - R_f)(q - c)); the
    coordinate-wise median of those centres ignores gross tracking errors up to ~50 %."""
    frames = np.flatnonzero(valid.any(axis=1))
    order = frames[np.argsort(a[frames])]
    third = max(1, order.size // 3)
    lo, hi = order[:third], order[-third:]
    cs, sn = np.cos(a), np.sin(a)
    cands = []
    for k in range(valid.shape[1]):
        f = lo[valid[lo, k]]
        g = hi[valid[hi, k]]
        if f.size == 0 or g.size == 0:
            continue
        f, g = np.repeat(f, g.size), np.tile(g, f.size)
        al, be = cs[g] - cs[f], sn[g] - sn[f]  # R_g - R_f = al I + be J
        den = al * al + be * be
        ok = den > 1e-12
        f, g, al, be, den = f[ok], g[ok], al[ok], be[ok], den[ok]
        ux, uy = Px[g, k] - Px[f, k], Py[g, k] - Py[f, k]
        dx, dy = (al * ux + be * uy) / den, (al * uy - be * ux) / den
        cands.append(np.stack([Px[f, k] - (cs[f] * dx - sn[f] * dy),
                               Py[f, k] - (sn[f] * dx + cs[f] * dy)], axis=1))
    if not cands:
        return
    c = np.median(np.concatenate(cands), axis=0)
    # q_k: the median of each feature's detections turned back to angle 0
    ex, ey = Px - c[0], Py - c[1]
    qxy = np.concatenate([cs[:, None] * ex + sn[:, None] * ey,
                          cs[:, None] * ey - sn[:, None] * ex], axis=1)  # (F, 2K)
    vv = np.concatenate([valid, valid], axis=1)
    srt = np.sort(np.where(vv, qxy, np.inf), axis=0)  # misses sort last
    n = vv.sum(axis=0)
    med = srt[np.maximum(n - 1, 0) // 2, np.arange(n.size)]  # lower median, one sort
    K = valid.shape[1]
    q = np.where((n[:K] > 0)[:, None], c + np.stack([med[:K], med[K:]], axis=1), st.q)
    st.c, st.q, st.a = c, q, a


def _norms(Px: np.ndarray, Py: np.ndarray,
           st: _State) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    r = _residuals(Px, Py, st)
    return np.hypot(*r), r


def fit_rigid(inp: SolveInputs, estimate_angles: bool) -> CentreResult:
    """Rigid-body centre fit; ``estimate_angles`` selects ``rigid`` over ``rigid-known``."""
    method = "rigid" if estimate_angles else "rigid-known"
    valid = inp.valid.copy()
    F, K = valid.shape
    # a feature seen once adds two unknowns and two equations: nothing to learn from it
    valid &= (valid.sum(axis=0) >= 2)[None, :]
    frames = valid.any(axis=1)
    if np.count_nonzero(frames) < 3:
        raise SolveError(f"{method}: fewer than 3 usable frames (features seen at least twice "
                         f"appear in {np.count_nonzero(frames)} frames)")
    readback = inp.angles_rad.copy()
    spread = float(np.rad2deg(np.ptp(readback[frames])))
    o = np.nanmean(inp.points[valid], axis=0)
    Px = np.where(valid, inp.points[..., 0] - o[0], 0.0)
    Py = np.where(valid, inp.points[..., 1] - o[1], 0.0)
    vf = valid.astype(float)
    a0 = readback
    if spread < MIN_SPREAD_DEG:
        if not estimate_angles:
            raise SolveError(f"{method}: no angular spread in the readback "
                             f"(angles span {spread:.2g} deg); use 'rigid' or 'circles'")
        a_img = image_angles(np.stack([Px, Py], axis=-1), valid)
        ok = np.isfinite(a_img)
        spread_img = float(np.rad2deg(np.ptp(a_img[ok]))) if ok.any() else 0.0
        if spread_img < MIN_SPREAD_DEG:
            raise SolveError(f"{method}: no angular spread (the features do not turn: "
                             f"{spread_img:.2g} deg between frames)")
        a0 = np.where(ok, a_img + readback.mean(), readback)
    st = _State(np.zeros(2), np.zeros((K, 2)), a0.copy())

    # Stage 1: a high-breakdown start, Huber IRLS at the starting angles (linear and convex),
    # then, for free angles, Huber IRLS on the full model.
    n_obs = 2 * int(valid.sum())
    p_glob = 2 + 2 * int(np.count_nonzero(valid.any(axis=0)))
    dof_corr = np.sqrt(n_obs / max(n_obs - p_glob, 1))
    _pair_start(Px, Py, valid, a0, st)
    sigma = 0.0
    # with free angles this only starts the next loop: a few iterations suffice
    for _ in range(3 if estimate_angles else _MAX_HUBER):
        nrm, _ = _norms(Px, Py, st)
        sigma = robust_sigma_2d(nrm[valid]) * dof_corr
        c_old = st.c
        _solve_known(Px, Py, vf * huber_weights(nrm, sigma), a0, st)
        if np.hypot(*(st.c - c_old)) < 1e-2 * max(sigma, 1e-6):
            break
    r: tuple[np.ndarray, np.ndarray] | None
    if estimate_angles:
        known = _State(st.c, st.q, st.a)
        nrm, _ = _norms(Px, Py, st)
        sigma_known = robust_sigma_2d(nrm[valid])
        for _ in range(_MAX_HUBER):
            nrm, r = _norms(Px, Py, st)
            sigma = robust_sigma_2d(nrm[valid]) * dof_corr
            _, step = _gn_free(Px, Py, vf * huber_weights(nrm, sigma), st, r)
            if step < 0.1 * max(sigma, 1e-6):
                break
        nrm, _ = _norms(Px, Py, st)
        if robust_sigma_2d(nrm[valid]) > sigma_known:
            # the free model contains the known one, so a worse fit means frames' angles
            # locked onto their gross errors (most of a frame's features wrong): restart the
            # rejection from the known-angle fit
            log.debug("%s: free-angle Huber fit worse than known-angle start; restarting",
                      method)
            st = known

    # Stage 2: hard rejection, refit on inliers until the inlier set is stable.
    nrm, r = _norms(Px, Py, st)
    sigma = robust_sigma_2d(nrm[valid]) * dof_corr
    mask = valid & (nrm <= CUT_2D * max(sigma, 1e-12))
    H = None
    for it in range(_MAX_MASK):
        wm = mask.astype(float)
        if estimate_angles:
            # nearly linear in the parameters: Gauss-Newton converges in a step or two
            for _ in range(_MAX_GN):
                H, step = _gn_free(Px, Py, wm, st, r)
                r = None
                if step < 0.25 * max(sigma, 1e-6) + 1e-12:
                    break
        else:
            H = _solve_known(Px, Py, wm, a0, st)
        nrm, r = _norms(Px, Py, st)
        n_in = int(mask.sum())
        n_par = 2 + 2 * int(np.count_nonzero(mask.any(axis=0)))
        if estimate_angles:
            n_par += int(np.count_nonzero(mask.any(axis=1))) - 1
        dof = 2 * n_in - n_par
        if dof <= 0:
            raise SolveError(f"{method}: not enough inlier detections ({n_in}) for "
                             f"{n_par} unknowns")
        sigma = float(np.sqrt(np.sum(nrm[mask] ** 2) / dof))
        new_mask = valid & (nrm <= CUT_2D * max(sigma, 1e-12))
        if np.array_equal(new_mask, mask) or it == _MAX_MASK - 1:
            break  # (if it never settles, report the set the last fit used)
        mask = new_mask
    assert H is not None
    if estimate_angles:
        _check_spread(method, st.a, mask)
    unit = _centre_cov(method, H, 1.0)
    # with the readback's angles taken as exact, a frame's angle error turns the features
    # about the centre (their mean moves with it) and each one's path its own way: sigma
    # already holds that misfit, and either term would count it again (the covariance came
    # out 8 times too large on a 2 % scale error). Free angles (the procedures') only.
    excess, sigma_t = np.zeros((2, 2)), 0.0
    if estimate_angles:
        excess = _features_excess(Px, Py, mask, st.a, sigma)
        sigma_t = _translation_sigma(*_residuals(Px, Py, st), mask, st.a)
    cov = unit * max(sigma, sigma_t) ** 2 + excess
    if estimate_angles:
        act = mask.any(axis=1)
        delta = float(np.mean(readback[act] - st.a[act]))
        cd, sd = np.cos(-delta), np.sin(-delta)
        d = st.q - st.c
        st.q = st.c + np.stack([cd * d[:, 0] - sd * d[:, 1], sd * d[:, 0] + cd * d[:, 1]], -1)
        angles = np.rad2deg(np.where(act, st.a + delta, np.nan))
    else:
        angles = np.rad2deg(a0)
    n_in = int(mask.sum())
    outliers = int(np.count_nonzero(inp.valid & ~mask))
    log.debug("%s: centre %s, sigma %.3g px, %d inliers, %d outliers", method, st.c + o,
              sigma, n_in, outliers)
    return CentreResult(center_px=st.c + o, cov_px2=cov, method=method,
                        rms_residual_px=float(np.sqrt(np.mean(nrm[mask] ** 2) / 2.0)),
                        inliers=n_in, outliers=outliers, inlier_mask=mask,
                        angles_deg=angles, n_frames=F,
                        extra={"sigma_px": sigma, "sigma_translation_px": sigma_t,
                               "cov_independent_px2": unit * sigma**2,
                               "features_excess_px2": excess,
                               "template_px": st.q + o})


def _feature_centres(Px: np.ndarray, Py: np.ndarray, mask: np.ndarray, a: np.ndarray
                     ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each feature's own centre (its path alone, at the fit's angles) and its covariance
    per unit noise; features seen in fewer than 3 frames are left out."""
    cs, sn = np.cos(a), np.sin(a)
    cents: list[np.ndarray] = []
    covs: list[np.ndarray] = []
    for k in range(mask.shape[1]):
        f = np.flatnonzero(mask[:, k])
        if f.size < 3:
            continue
        c, s = cs[f], sn[f]
        # p = (I - R) c + R q, unknowns (cx, cy, qx, qy)
        A = np.concatenate([np.stack([1 - c, s, c, -s], 1), np.stack([-s, 1 - c, s, c], 1)])
        b = np.concatenate([Px[f, k], Py[f, k]])
        N = A.T @ A
        try:
            Ni = np.linalg.inv(N)
        except np.linalg.LinAlgError:
            continue
        cents.append((Ni @ (A.T @ b))[:2])
        covs.append(Ni[:2, :2])
    return cents, covs


def _features_excess(Px: np.ndarray, Py: np.ndarray, mask: np.ndarray, a: np.ndarray,
                     sigma: float) -> np.ndarray:
    """What the features' own centres disagree by beyond the noise: a covariance to add.

    Every feature turns about the one centre, so each one's path alone gives it. A texture,
    a shadow or clutter under one corner biases that corner's path as the holder turns
    across them: its centre then leaves the others' by more than their noise allows, and
    the fitted centre, their weighted mean, carries part of that bias, which no residual
    shows (a bias that changes smoothly with the angle is absorbed by the fit). When the
    centres scatter beyond their noise (chi-square above its degrees of freedom), the
    excess tau^2 per axis is the Paule-Mandel estimate, as between sweeps
    (``alignd.procedures.sweep.CentrePool``), and the mean's covariance grows by what tau^2
    adds to it. Significant means beyond the 95 % point: independent noise then adds
    nothing 19 times in 20 (at the chi-square's mean half the sweeps would gain a little).
    """
    cents, units = _feature_centres(Px, Py, mask, a)
    dof = 2 * (len(cents) - 1)
    if dof <= 0 or sigma <= 0:
        return np.zeros((2, 2))
    covs = [u * sigma**2 for u in units]
    plain = weighted_mean(cents, covs)
    if plain.q <= float(chi2_dist.ppf(EXCESS_LEVEL, dof)):
        return np.zeros((2, 2))
    return weighted_mean(cents, covs, paule_mandel(cents, covs)).cov - plain.cov


def _check_spread(method: str, a: np.ndarray, mask: np.ndarray) -> None:
    act = mask.any(axis=1)
    spread = float(np.rad2deg(np.ptp(a[act])))
    if spread < MIN_SPREAD_DEG:
        raise SolveError(f"{method}: no angular spread (estimated angles span {spread:.2g} deg)")


def _centre_cov(method: str, H: np.ndarray, sigma: float) -> np.ndarray:
    """sigma^2 times the centre block of H^-1, refusing an undetermined centre."""
    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError as exc:
        raise SolveError(f"{method}: centre not determined (singular normal equations)") from exc
    cc = Hinv[:2, :2]
    cc = 0.5 * (cc + cc.T)
    ev = np.linalg.eigvalsh(cc)
    if not np.all(np.isfinite(ev)) or ev[0] <= 0 or ev[-1] * max(abs(H[0, 0]), 1e-300) > 1e12:
        raise SolveError(f"{method}: centre not determined by the data (ill-conditioned; "
                         "no angular spread or degenerate geometry)")
    return cc * sigma**2


def _translation_sigma(rx: np.ndarray, ry: np.ndarray, mask: np.ndarray,
                       a: np.ndarray) -> float:
    """The scale of the frames' mean residual, per feature, from frame to frame.

    The centre is read from how the features translate together from frame to frame
    (``(I - R) c`` moves them all alike), so its uncertainty follows the noise of the
    frames' mean residual. With independent errors that is sigma / sqrt(n); corners found
    as crossings of a holder's sides err together (each side's offset moves its two
    corners alike), and the mean then scatters more than that (by about 1.3 where each
    side's offset errs alone; 1.16 over the randomised corpus' sweeps). It is measured from
    the differences between neighbouring frames (in angle order): a turntable's error
    motion also moves every feature alike, but smoothly with the angle, so it stays out
    (it is the runout map's and the floor's to count, and a stale map must still show
    as sweeps that disagree). n_f times the mean's variance, per axis; 0 with one feature
    or fewer than 6 frames.
    """
    n = mask.sum(axis=1)
    if np.count_nonzero(mask.any(axis=0)) < 2:
        return 0.0
    act = np.flatnonzero(n > 0)
    act = act[np.argsort(a[act])]
    if act.size < 6:
        return 0.0
    nf = n[act].astype(float)
    mx = np.sum(np.where(mask, rx, 0.0), axis=1)[act] / nf
    my = np.sum(np.where(mask, ry, 0.0), axis=1)[act] / nf
    d2 = np.diff(mx) ** 2 + np.diff(my) ** 2
    w = 1.0 / nf[1:] + 1.0 / nf[:-1]
    return float(np.sqrt(np.mean(d2 / w) / 2.0))
