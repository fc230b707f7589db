"""bench/vision.py's side pre-check rows: the frame count asked for is the one averaged,
and the errors are listed by how the views were coded (what limits them differs: noise on
raw frames, coding error the frames share on JPEG ones; docs/vision.md)."""

from __future__ import annotations

import argparse
import math
from types import ModuleType

import pytest
from bench_modules import load_bench

from alignd.config import PrecheckConfig


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_bench("vision")


def test_side_rows_average_the_frames_asked_for_and_split_by_coding(
        bench: ModuleType) -> None:
    assert PrecheckConfig().tilt_frames == bench.TILT_FRAMES
    # one view per category (seeded): the JPEG one among them
    rows, summary = bench.corpus_side(5, 2224, frames=3, u_target=None)
    names = [r[0] for r in rows]
    assert "ROI x3: total" in names and "auto x3: total" in names
    assert not any(f"x{bench.TILT_FRAMES}" in n for n in names)
    bands = [r for r in rows if r[0].startswith("  ")]
    # under each pre-check total: the raw views and the JPEG one's quality band
    assert sum(int(r[1]) for r in bands) == 2 * 5
    assert sum(1 for r in bands if r[0] == "  not JPEG") == 2
    assert sum(1 for r in bands if r[0].startswith("  JPEG q")) == 2
    assert summary["ROI_found"] == 1.0 and summary["ROI_wrong"] == 0
    # three frames of noisy views: well inside a tenth of a degree, not exact
    assert 0 < summary["ROI_pre_max"] < 0.02 and math.isfinite(summary["ROI_pre_rms"])
    assert summary["ROI_frames"] == 3 and summary["ROI_more"] == 0


def test_side_rows_take_frames_as_the_pre_check_does(bench: ModuleType) -> None:
    """With a target uncertainty the pre-check rows take more frames as the pre-check
    would, up to the most allowed (a target no view reaches: every view doubles once),
    and the table says so in its labels and its frames row."""
    assert PrecheckConfig().tilt_u_target_deg == bench.TILT_U_TARGET
    rows, summary = bench.corpus_side(2, 2224, frames=3, u_target=1e-6, max_frames=6)
    names = [r[0] for r in rows]
    assert "ROI x3+: total" in names and "auto x3+: total" in names
    for mode in ("ROI", "auto"):
        assert summary[f"{mode}_frames"] == 6 and summary[f"{mode}_more"] == 2
    frames_row = [t for t in bench.side_targets(summary, 3, 1e-6)
                  if t[0].startswith("side: pre-check frames")]
    assert frames_row and frames_row[0][1] == "6.0, 6 (2) / 6.0, 6 (2)"


def test_frame_size_option(bench: ModuleType) -> None:
    """--size WxH: the corpus drawn at a camera's own frame size; nonsense refused."""
    assert bench._frame_size("1920x1080") == (1920, 1080)
    assert bench._frame_size("640X480") == (640, 480)
    for bad in ("1920", "axb", "320x240", "640x400"):
        with pytest.raises(argparse.ArgumentTypeError):
            bench._frame_size(bad)
    _rows, summary = bench.corpus_top(2, 2124, (640, 480))
    assert summary["n"] == 2 and summary["found"] == 1.0


def test_side_disc_rows_draw_the_views_through_a_lens_out_of_focus(
        bench: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    """The side corpus again, each view blurred by a disc (a lens out of focus): its rows
    name the disc and score the pre-check against the same 0.002 deg target, and the
    edges measured take the disc model."""
    rows = bench.side_disc_corpus(2, 2224, frames=3, u_target=None)
    names = [r[0] for r in rows]
    assert names[0] == "side, defocused by a disc (2 views), regions: found (%)"
    assert any("tilt max error, pre-check (3 frames)" in n and r[2] == "<= 0.002"
               for n, r in zip(names, rows, strict=True))
    assert rows[0][1] == "100.00" and rows[0][3] is True
    seen: list[object] = []
    real = bench.measure_tilt_frames

    def spy(*args: object, **kwargs: object) -> object:
        av = real(*args, **kwargs)
        seen.extend(e.spread for f in av.frames for e in (*f.sample_edges, *f.pole_edges))
        return av

    monkeypatch.setattr(bench, "measure_tilt_frames", spy)
    bench.side_disc_corpus(1, 2224, frames=2, u_target=None)
    assert seen and set(seen) == {"disc"}
