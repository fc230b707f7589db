"""Tracking with the previous frame's detection as hint: the profile fit reuses each
side's blur width when every side held (moved by less than a pixel), which skips its blur
estimate, and gives the corners it gives without the shortcut; a holder that moved gets
its blur measured anew. Likewise a held holder beside no penumbra is not looked at for one
again (its corners the same as with the look), and one beside a penumbra is."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import alignd.vision.profile_fit as profile_fit
from alignd.vision.holder import HolderDetection, order_corners, track_holder
from drivers.config import SimWorldConfig
from drivers.sim.render import RenderOptions, posed_world, render_top, top_truth

_OPTS = RenderOptions(gradient=(0.2, 0.1))


_CAST = RenderOptions(gradient=(0.2, 0.1), cast_shadow_depth=0.3)  # the holder's shadow


def _frame(turntable_deg: float, rng: np.random.Generator, opts: RenderOptions = _OPTS
           ) -> tuple[np.ndarray, np.ndarray]:
    w = posed_world(SimWorldConfig(yaw_deg=1.2), seed=3, turntable_deg=turntable_deg)
    sc, cam = w.top_scene(), w.top_camera
    truth = np.asarray(top_truth(sc, cam, opts)["corners_px"], float)
    return render_top(sc, cam, opts, rng), truth


def _count_penumbra_looks(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls = [0]
    real = profile_fit._penumbra_bend

    def counted(*args: object) -> object:
        calls[0] += 1
        return real(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(profile_fit, "_penumbra_bend", counted)
    return calls


def _count_blur_fits(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls = [0]
    real = profile_fit._fit

    def counted(*args: np.ndarray | int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        calls[0] += 1
        return real(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(profile_fit, "_fit", counted)
    return calls


def test_a_held_holder_reuses_the_blur_and_keeps_its_corners(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(11)
    img0, _ = _frame(4.0, rng)
    prev = track_holder(img0)
    assert prev.ok and len(prev.side_blur_px) == 4
    assert all(0.3 < b < 3.0 for b in prev.side_blur_px)
    calls = _count_blur_fits(monkeypatch)
    err_reuse, err_fresh = [], []
    for k in range(1, 9):  # sub-pixel steps with fresh noise: a tracked sequence
        img, truth = _frame(4.0 + 0.02 * k, rng)
        before = calls[0]
        fresh = track_holder(img, hint=prev.corners_px)
        # corners alone: the blur is estimated (once more in a wider window for a soft edge)
        assert calls[0] > before
        estimated = calls[0]
        reused = track_holder(img, hint=prev)
        assert calls[0] == estimated  # the detection: its blur is reused
        assert reused.ok and fresh.ok
        assert reused.side_blur_px == prev.side_blur_px
        got_r = order_corners(reused.corners_px, truth)
        got_f = order_corners(fresh.corners_px, truth)
        # the same corners within a hundredth of the corner noise's bound
        assert np.max(np.linalg.norm(got_r - got_f, axis=1)) < 0.01
        err_reuse += list(np.linalg.norm(got_r - truth, axis=1))
        err_fresh += list(np.linalg.norm(got_f - truth, axis=1))
        prev = reused
    rms_r, rms_f = float(np.sqrt(np.mean(np.square(err_reuse)))), \
        float(np.sqrt(np.mean(np.square(err_fresh))))
    assert rms_r < 0.05 and abs(rms_r - rms_f) < 0.002


def test_a_holder_that_moved_gets_its_blur_measured(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(12)
    img0, _ = _frame(4.0, rng)
    prev = track_holder(img0)
    img, truth = _frame(5.0, rng)  # a degree: the corners move by pixels
    assert np.max(np.linalg.norm(order_corners(truth, prev.corners_px) - prev.corners_px,
                                 axis=1)) > 1.5
    calls = _count_blur_fits(monkeypatch)
    det = track_holder(img, hint=prev)
    assert det.ok and calls[0] >= 1
    assert det.side_blur_px != prev.side_blur_px
    assert np.max(np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)) < 0.2


def test_a_detection_without_blurs_is_a_plain_corner_hint() -> None:
    rng = np.random.default_rng(13)
    img, _ = _frame(4.0, rng)
    prev = track_holder(img, refine="area")
    assert prev.ok and prev.side_blur_px == ()
    a = track_holder(img, hint=prev)
    b = track_holder(img, hint=prev.corners_px)
    np.testing.assert_array_equal(a.corners_px, b.corners_px)
    assert isinstance(prev, HolderDetection)


def test_a_held_holder_beside_no_penumbra_is_not_looked_at_for_one(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(21)
    prev = track_holder(_frame(4.0, rng)[0])
    assert prev.ok and not prev.penumbra
    looks = _count_penumbra_looks(monkeypatch)
    for k in range(1, 4):
        img, truth = _frame(4.0 + 0.02 * k, rng)
        det = track_holder(img, hint=prev)
        assert looks[0] == 0 and det.ok and not det.penumbra
        # looked for, none is found: the same corners to the last bit
        looked = track_holder(img, hint=replace(prev, penumbra=True))
        assert looks[0] == 1 and not looked.penumbra
        np.testing.assert_array_equal(det.corners_px, looked.corners_px)
        assert np.max(np.linalg.norm(order_corners(det.corners_px, truth) - truth,
                                     axis=1)) < 0.1
        looks[0] = 0
        prev = det


def test_a_held_holder_beside_a_penumbra_is_fitted_with_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(22)
    prev = track_holder(_frame(4.0, rng, _CAST)[0])
    assert prev.ok and prev.penumbra  # its cast shadow's penumbra beside a side
    looks = _count_penumbra_looks(monkeypatch)
    img, truth = _frame(4.02, rng, _CAST)
    det = track_holder(img, hint=prev)
    assert looks[0] >= 1 and det.ok and det.penumbra
    # (measured 0.014 px; not looked for, the same frame's corners are 0.035 px off)
    err = np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)
    assert float(err.max()) < 0.025
    unlooked = track_holder(img, hint=replace(prev, penumbra=False))
    assert not unlooked.penumbra
    err_un = np.linalg.norm(order_corners(unlooked.corners_px, truth) - truth, axis=1)
    assert float(err_un.max()) > float(err.max()) + 0.01
