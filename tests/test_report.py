"""Issue 14: the report figure reads the same in every run: a fixed scale, labels that
never cover each other, error bars that say when they leave the axis, the text block."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from alignd import report


def _run(offsets: list[tuple[float, float]], U: float = 4.0, kind: str = "align",
         tol: float = 10.0, cov_px2: float = 1e-4) -> dict[str, Any]:
    recs = []
    for i, (x, y) in enumerate(offsets):
        recs.append({"n": i + 1, "iteration": i + 1,
                     "kind": "verify" if kind == "align" and i == len(offsets) - 1 else kind,
                     "centre_px": [640.0, 360.0], "cov_centre_px2": np.eye(2).tolist(),
                     "offset_um": [x, y], "offset_norm_um": float(np.hypot(x, y)), "U_um": U,
                     "cov_offset_um2": (np.eye(2) * (U / 2) ** 2 / 2).tolist(),
                     "scale_px_per_mm": 6.5})
    recs[0]["cov_centre_px2"] = (np.eye(2) * cov_px2).tolist()
    return {"id": 1, "kind": kind, "verdict": "aligned", "reason": "ok",
            "config": {"procedure": {"tolerance_um": tol}}, "iteration_records": recs,
            "result": {"verdict": "aligned"}}


def _mask(img: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    return np.all(np.abs(img.astype(int) - colour) < 40, axis=2)


def test_zoom_scale_does_not_depend_on_the_run() -> None:
    """The tolerance circle and the scale bar land on the same pixels whatever the run's
    offsets and uncertainties (the old figure magnified the ellipse per run)."""
    a = report.draw_zoom(_run([(2000.0, 300.0), (3.0, 1.0)], U=9.0, cov_px2=1e-6))
    b = report.draw_zoom(_run([(0.2, 0.1)], U=0.5, cov_px2=1e-2))
    tol_a, tol_b = _mask(a, report.TOL_COLOUR), _mask(b, report.TOL_COLOUR)
    circle = np.zeros_like(tol_a)
    circle[30:, :] = True  # below the title (the tolerance label may move)
    ys, xs = np.nonzero(tol_a & circle)
    r = np.hypot(xs - xs.mean(), ys - ys.mean())
    assert (tol_a & tol_b).sum() > 0.6 * tol_a.sum()
    # the circle's radius is tolerance * fixed px/um: field = ZOOM_FIELD_TOLERANCES * tol
    plot = report.PLOT_H - 28 - 10
    assert abs(np.median(r) - plot / report.ZOOM_FIELD_TOLERANCES) < 4


def test_zoom_shows_far_offsets_as_arrows_on_the_edge() -> None:
    img = report.draw_zoom(_run([(2000.0, 0.0), (1.0, 1.0)]))
    red = _mask(img, report.ALIGN_COLOUR)
    w = red.shape[1]
    plot = report.PLOT_H - 28 - 10
    right = (w - plot) // 2 + plot
    ys, xs = np.nonzero(red)
    assert right - 10 <= xs.max() <= right  # the arrow's tip on the field's right edge
    tip_rows = ys[xs >= right - 10]
    assert abs(tip_rows.mean() - (28 + plot / 2)) < 4  # at the height of the axis (y = 0)


def test_labels_never_overlap() -> None:
    img = np.zeros((200, 300, 3), np.uint8)
    labels = report.Labels(img)
    placed = [labels.put(f"{v:.3g}", (150, 100), (255, 255, 255)) for v in range(12)]
    assert sum(placed) >= 8
    for a, b in itertools.combinations(labels.boxes, 2):
        assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1], (a, b)


def test_convergence_bar_below_zero_ends_in_an_arrow_not_a_cap() -> None:
    run = _run([(3.0, 0.0), (0.4, 0.0)], U=9.0)
    img = report.draw_convergence(run)
    bar = _mask(img, (200, 80, 0))
    h = img.shape[0]
    y1 = h - 42
    cols = np.nonzero(bar[y1 - 3])[0]
    assert len(cols) >= 2  # both bars reach the axis' bottom
    # the markers are distinct: one align circle, one verify diamond
    assert _mask(img, report.ALIGN_COLOUR).any() and _mask(img, report.VERIFY_COLOUR).any()


def test_convergence_labels_do_not_collide_for_a_repeated_iteration() -> None:
    """Iteration 3 measured twice (align, then verify) gets two x positions and labels."""
    run = _run([(2000.0, 0.0), (4.0, 0.0), (0.5, 0.0), (0.55, 0.0)])
    run["iteration_records"][3]["iteration"] = 3
    ms = report._measurements(run)
    assert [m.label for m in ms] == ["1", "2", "3", "v3"]
    img = report.draw_convergence(run)
    assert img.shape == (report.PLOT_H, report.WIDTH - report.PLOT_H, 3)


def test_report_carries_the_decision_rule_budget_and_reason() -> None:
    run = _run([(1.0, 0.0)])
    run["result"].update(
        decision={"rule": "guarded", "rule_name": "guarded acceptance (ISO 14253-1)",
                  "tolerance_um": 10.0, "offset_um": 1.0, "U_um": 3.0, "guard_band_um": 3.0,
                  "accept_below_um": 7.0, "reject_above_um": 13.0,
                  "text": "within 10 um: offset 1.0 um, U 3.0 um"},
        budget={"contributions": [{"name": "centre fit", "u_um": 1.2, "type": "A"},
                                  {"name": "pixel scale", "u_um": 0.3, "type": "B"}],
                "combined_um": 1.24, "k": 2.0, "U_um": 2.48})
    assert report.report_notes(run) == ["verdict: aligned: ok"]
    panel = report.draw_verdict(run)
    empty = report.draw_verdict({"result": {}})
    assert panel.shape == empty.shape == (report.VERDICT_H, report.WIDTH, 3)
    assert (panel != empty).any()  # the zones, the measurement and the budget are drawn
    img = report.render_report(run, np.full((720, 1280), 128, np.uint8))
    assert img.shape == (report.HEADER_H + 540 + report.VERDICT_H + report.PLOT_H
                         + report.NOTES_H, report.WIDTH, 3)
    notes = img[-report.NOTES_H:]
    assert (notes < 100).any()  # the text is there


def test_report_notes_give_the_prechecks_readings() -> None:
    run = _run([(1.0, 0.0)])
    run["result"].update(tilt_deg=0.3002, tilt_u_deg=0.00012, eccentricity=0.0094)
    assert report.report_notes(run) == [
        "verdict: aligned: ok",
        "pre-checks: sample tilt +0.3002 +/- 0.0001 deg (u, k=1); "
        "top-camera rim eccentricity 0.0094"]
    run["result"].update(eccentricity_u=0.00043)
    assert report.report_notes(run)[1].endswith(
        "top-camera rim eccentricity 0.0094 +/- 0.0004 (u, k=1)")
    run["result"].update(tilt_u_deg=None, eccentricity=None)
    assert report.report_notes(run)[1] == "pre-checks: sample tilt +0.3002 deg"
    run["result"].update(tilt_deg=None)
    assert report.report_notes(run) == ["verdict: aligned: ok"]


def test_report_notes_give_the_runs_warnings() -> None:
    """A run that could not decide often says why only in a warning (a lens not modelled,
    a stale runout map): the picture carries them under the verdict."""
    run = _run([(1.0, 0.0)])
    run["details"] = {"warnings": ["align sweep 1: the holder's corners disagree with one "
                                   "rigid turn far beyond their noise"]}
    assert report.report_notes(run) == [
        "verdict: aligned: ok",
        "warning: align sweep 1: the holder's corners disagree with one rigid turn far "
        "beyond their noise"]
    img = report.draw_notes(run)
    assert img.shape[0] == report.NOTES_H
    assert (img[40:60] < 100).any()  # the warning's line is drawn
    # many warnings grow the panel, up to its most; the JSON has the rest
    run["details"]["warnings"] = [f"warning number {k} " + "word " * 30 for k in range(12)]
    tall = report.draw_notes(run)
    assert tall.shape[0] == report.NOTES_MAX_H
    assert (tall[-30:] < 100).any()


def test_a_label_stays_inside_its_box() -> None:
    """A label's white halo ends where its box ends: drawn with a thicker stroke, the halo
    had a wider glyph advance and ran 10-20 px past the text over a dark frame."""
    img = np.zeros((60, 400, 3), np.uint8)
    labels = report.Labels(img)
    assert labels.put("[17.5, 0]: 2.14 mm from the axis", (20, 30), (0, 120, 0), 0.45)
    x0, _, x1, _ = labels.boxes[0]
    _, xs = np.nonzero(img.max(axis=2) > 0)
    assert xs.min() >= x0 - 2 and xs.max() <= x1 + 2, (xs.min(), xs.max(), labels.boxes)


def test_a_refused_holder_frame_is_drawn_with_its_targets() -> None:
    """A run refused on its holder frame says "check the target on the run's picture":
    the picture draws the axis and the targets the verdict compares, at their offsets."""
    run = {"id": 1, "kind": "align", "verdict": "fault", "reason": "refused: target ...",
           "config": {"procedure": {"tolerance_um": 10.0}}, "iteration_records": [],
           "result": {"verdict": "fault"},
           "details": {"holder_frame_refused": {
               "centre_px": [640.0, 360.0], "targets": [
                   {"role": "config", "target_mm": [0.0, -17.5], "offset_mm": 35.3,
                    "offset_px": [0.0, -230.0]},
                   {"role": "fix", "target_mm": [0.0, 17.5], "offset_mm": 2.1,
                    "offset_px": [0.0, 14.0]}]}}}
    frame = np.full((720, 1280), 120, np.uint8)
    view = report.draw_top_view(run, frame)
    s = report.WIDTH / 1280
    magenta = _mask(view, report.REFUSED_STYLE["config"][0])
    green = _mask(view, report.REFUSED_STYLE["fix"][0])
    near = np.zeros_like(magenta)
    cy, cx = round(130 * s), round(640 * s)
    near[cy - 12:cy + 12, cx - 12:cx + 12] = True
    assert (magenta & near).sum() > 40  # the configured target's ring, 230 px above
    near[:] = False
    cy = round(374 * s)
    near[cy - 12:cy + 12, cx - 12:cx + 12] = True
    assert (green & near).sum() > 40
    # an old record's unreadable evidence draws nothing rather than a wrong mark
    run["details"]["holder_frame_refused"] = {"centre_px": [1.0]}
    report.draw_top_view(run, frame)


def test_a_run_without_sweeps_shows_its_last_saved_frame_named() -> None:
    """A run that ended before any sweep (the holder not found) keeps the frame the
    pre-check looked at: the picture draws it, captioned with its label."""
    run = {"frames": [{"hash": "ab12", "label": "precheck-holder"}], "sweeps": []}
    pick = report.pick_frame(run)
    assert pick is not None and pick["hash"] == "ab12" and pick["label"] == "precheck-holder"
    frame = np.full((720, 1280), 120, np.uint8)
    view = report.draw_top_view(run, frame)
    assert view[8:30, 10:300].max() == 255  # the caption, white on the frame's grey


def test_a_run_stopped_at_the_tilt_precheck_draws_its_last_top_frame_not_a_side_one() -> None:
    """The pre-check's side frames are in the record, but the view is drawn at the top
    camera's scale (its scale bar, the stage directions): a run refused for the tilt
    shows the last top frame (the rim's), not the side camera's pole and sample."""
    run = {"frames": [{"hash": "aa01", "label": "precheck-rim-007"},
                      {"hash": "bb02", "label": "precheck-side-000"},
                      {"hash": "cc03", "label": "precheck-side-001"}], "sweeps": []}
    pick = report.pick_frame(run)
    assert pick is not None and pick["hash"] == "aa01" and pick["label"] == "precheck-rim-007"
    only_side = {"frames": run["frames"][1:], "sweeps": []}
    assert report.pick_frame(only_side) is None


def test_the_side_panel_draws_the_edges_found_in_the_first_side_frame() -> None:
    """A run with side frames in its record draws the first one, its edges found again
    (the sample's red, the pole's green, each on its edge in the frame scaled to half the
    width), beside the pre-check's mean tilt; a frame where no edge is found says so."""
    from alignd.report_side import POLE_INK, SAMPLE_INK, draw_side_panel, side_frame_hash
    from drivers.config import SimWorldConfig
    from drivers.sim.render import RenderOptions, posed_world, render_side, side_truth

    sc = posed_world(SimWorldConfig(tilt_deg=0.3), seed=1).side_scene()
    img = render_side(sc, RenderOptions(), np.random.default_rng(1))
    truth = side_truth(sc, RenderOptions())
    run = _run([(3.0, 1.0)])
    run["frames"] = [{"hash": f"h{k}", "label": f"precheck-side-{k:03d}"} for k in range(8)]
    run["result"].update(tilt_deg=0.3001, tilt_u_deg=0.0001)
    assert side_frame_hash(run) == "h0"
    panel = draw_side_panel(run, img, report.WIDTH)
    scale = (report.WIDTH // 2) / img.shape[1]
    assert panel.shape[1] == report.WIDTH and panel.shape[0] == round(img.shape[0] * scale)
    mid = panel.shape[0] // 2
    row = panel[mid - 5:mid + 5, :report.WIDTH // 2]
    for ink, x in ((POLE_INK, truth["pole_x_px"]), (SAMPLE_INK, None)):
        cols = np.nonzero(_mask(row, ink).any(axis=0))[0]
        assert cols.size, ink
        if x is not None:  # the pole's two edges straddle its middle
            assert cols.min() < x * scale < cols.max()
    # the report stacks it above the notes; without a side frame, no panel
    full = report.render_report(run, None, img)
    assert full.shape[0] == report.render_report(run, None).shape[0] + panel.shape[0]
    blank = draw_side_panel(run, np.full_like(img, 128), report.WIDTH)
    assert not _mask(blank[:, :report.WIDTH // 2], SAMPLE_INK).any()
    assert not _mask(blank[:, :report.WIDTH // 2], POLE_INK).any()
    run["frames"] = [{"hash": "t0", "label": "align-1-000"}]
    assert side_frame_hash(run) is None


def test_the_side_panel_measures_the_frame_with_the_side_cameras_tone_curve_undone() -> None:
    """A side camera that encodes its values with a tone curve (cameras[].gamma) has it
    undone before its frames are measured, in the pre-check and so in the report's panel:
    on a frame lit unevenly down its height, the angles the panel prints are the
    linearised frame's, which differ from the coded frame's own."""
    from alignd.report_side import measure_again
    from alignd.vision.edges import linearise
    from alignd.vision.side import measure_tilt
    from drivers.config import SimWorldConfig
    from drivers.sim.render import RenderOptions, posed_world, render_side

    sc = posed_world(SimWorldConfig(tilt_deg=0.3), seed=1).side_scene()
    img = render_side(sc, RenderOptions(), np.random.default_rng(1)).astype(float)
    lit = img * np.linspace(1.0, 0.45, img.shape[0])[:, None]  # dimmer down the frame
    coded = np.clip(255 * (lit / 255) ** (1 / 2.2) + 0.5, 0, 255).astype(np.uint8)
    run = _run([(3.0, 1.0)])
    run["config"] = {"cameras": [{"role": "top", "gamma": 1.0},
                                 {"role": "side", "gamma": 2.2}]}
    m, why = measure_again(run, coded)
    assert m is not None and why == ""
    assert m.tilt_deg == measure_tilt(linearise(coded, 2.2)).tilt_deg
    raw = measure_tilt(coded).tilt_deg
    assert abs(m.tilt_deg - 0.3) < abs(raw - 0.3)  # (0.00002 against 0.00024 deg off)
    run["config"]["cameras"][1]["gamma"] = 1.0
    again = measure_again(run, coded)[0]
    assert again is not None and again.tilt_deg == raw
