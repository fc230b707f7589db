"""``alignctl analyze camera``: what a camera does to its frames, read from frames of a
still view (alignd.vision.camera_check), on both simulators' frames: our renderer's top
camera and the corpus's side views, each drawn linear and through a tone curve, and the
same frames sharpened, smoothed, JPEG-coded, clipped and with defective pixels."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from alignd.cli import main as alignctl_main
from alignd.errors import VisionError
from alignd.vision.camera_check import check_frames
from drivers.sim.render import RenderOptions, posed_world, render_top
from drivers.sim.scenes import SIDE_CATEGORIES, random_side_scene


def _top_frames(gamma: float, n: int = 8, seed: int = 11) -> list[np.ndarray]:
    """n frames of our renderer's still top view (the holder on the turntable)."""
    w = posed_world(seed=1)
    opts = RenderOptions(gamma=gamma, read_noise_dn=1.5, electrons_per_dn=40.0)
    rng = np.random.default_rng(seed)
    return [render_top(w.top_scene(), w.top_camera, opts, rng) for _ in range(n)]


def _side_frames(gamma: float, index: int) -> list[np.ndarray]:
    """The 8 frames of the corpus's side view ``index`` (seed 5, the categories in turn)."""
    rng = np.random.default_rng(5)
    for i in range(index):
        random_side_scene(rng, SIDE_CATEGORIES[i % len(SIDE_CATEGORIES)], frames=8, gamma=gamma)
    cat = SIDE_CATEGORIES[index % len(SIDE_CATEGORIES)]
    return list(random_side_scene(rng, cat, frames=8, gamma=gamma).frames)


def _sharpen(img: np.ndarray, amount: float = 1.0, radius: float = 1.0) -> np.ndarray:
    f = img.astype(np.float32)
    return np.clip(np.rint(f + amount * (f - cv2.GaussianBlur(f, (0, 0), radius))), 0,
                   255).astype(np.uint8)


def _levels(findings: list) -> dict[str, str]:  # type: ignore[type-arg]
    return {f.what.split(":")[0].split(" (")[0]: f.level for f in findings}


@pytest.mark.parametrize("gamma", [1.0, 2.2])
def test_the_tone_curve_is_read_from_the_noise_on_our_renderer(gamma: float) -> None:
    """Our top view has three levels (holder, turntable, floor), 130-245 DN apart through
    the curve: gamma is known to +-0.2-0.5 there, enough to tell 2.2 from linear."""
    c = check_frames(_top_frames(gamma))
    assert abs(c.gamma - gamma) <= 3 * c.gamma_u and c.gamma_u < 0.5
    assert abs(c.noise_correlation[0]) < 0.02 and abs(c.noise_correlation[1]) < 0.02
    acts = [f.what for f in c.findings if f.level == "act"]
    if gamma == 1.0:
        assert not acts
    else:
        assert len(acts) == 1 and "applies a tone curve" in acts[0]


@pytest.mark.parametrize("gamma", [1.0, 2.2])
@pytest.mark.parametrize("index,category", [(1, "sample on holder"), (2, "uneven light"),
                                            (4, "12-bit")])
def test_the_tone_curve_on_the_corpus_side_views(gamma: float, index: int,
                                                 category: str) -> None:
    """Views drawn by the corpus (its own noise model, 8- and 12-bit) whose levels span
    over 100 DN: gamma within 0.1."""
    assert SIDE_CATEGORIES[index % len(SIDE_CATEGORIES)] == category
    c = check_frames(_side_frames(gamma, index))
    assert c.level_span_dn[1] - c.level_span_dn[0] > 100
    assert c.gamma == pytest.approx(gamma, abs=0.1)
    assert c.bits == (12 if category == "12-bit" else 8)


def test_a_view_of_one_level_gives_no_gamma() -> None:
    rng = np.random.default_rng(2)
    frames = [np.clip(np.rint(120 + 2 * rng.standard_normal((120, 160))), 0, 255
                      ).astype(np.uint8) for _ in range(4)]
    c = check_frames(frames)
    assert np.isnan(c.gamma)
    assert any("not measured" in f.what and "span" in f.what for f in c.findings)
    assert c.noise_dn == pytest.approx(2.0, rel=0.1)


def test_sharpening_and_smoothing_are_told_by_the_noise() -> None:
    frames = _top_frames(1.0)
    sharp = check_frames([_sharpen(f) for f in frames])
    assert max(sharp.noise_correlation) < -0.05
    assert any(f.level == "act" and "sharpens" in f.what for f in sharp.findings)
    smooth = check_frames([cv2.GaussianBlur(f, (0, 0), 0.7) for f in frames])
    assert min(smooth.noise_correlation) > 0.3
    assert any("smooths" in f.what for f in smooth.findings)
    raw = check_frames(frames)
    assert not any("sharpens" in f.what or "smooths" in f.what for f in raw.findings)


def test_jpeg_clipping_and_defective_pixels() -> None:
    frames = _top_frames(1.0, n=3)
    coded = [cv2.imdecode(cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 75])[1],
                          cv2.IMREAD_GRAYSCALE) for f in frames]
    c = check_frames(coded)
    assert c.jpeg_quality == 75
    assert any(f.level == "act" and "JPEG" in f.what for f in c.findings)
    assert np.isnan(c.gamma)  # the coding reshapes the noise: not read
    assert check_frames(frames).jpeg_quality is None
    # 30 hot and 30 dead pixels at the same places in every frame, and a bright patch
    # at full scale
    rng = np.random.default_rng(4)
    ys, xs = rng.integers(10, 470, 60), rng.integers(10, 630, 60)
    bad = []
    for f in frames:
        g = f.copy()
        g[ys[:30], xs[:30]] = 255
        g[ys[30:], xs[30:]] = 0
        g[:120, :120] = 255  # 1.6 % of the frame
        bad.append(g)
    c = check_frames(bad)
    assert c.defective_pixels >= 55  # (a few may fall where the frame is already near 0/255)
    assert c.clipped_high > 120 * 120 / (frames[0].size) * 0.99
    lv = _levels(c.findings)
    assert any(k.endswith("at full scale") and v == "act" for k, v in lv.items())
    assert any("defective pixels" in k for k in lv)
    # a glint of 0.35 % of the frame at full scale is worth a note, not a new exposure
    for g in bad:
        g[:120, :120] = frames[0][:120, :120]
        g[:40, :80] = 255
    lv = _levels(check_frames(bad).findings)
    assert any(k.endswith("at full scale") and v == "note" for k, v in lv.items())


def test_frames_of_different_sizes_are_refused() -> None:
    with pytest.raises(VisionError, match="differ in size"):
        check_frames([np.zeros((40, 60), np.uint8), np.zeros((40, 61), np.uint8)])
    with pytest.raises(VisionError, match="no frames"):
        check_frames([])


def test_one_frame_says_what_it_cannot_measure() -> None:
    c = check_frames(_top_frames(2.2, n=1))
    assert np.isnan(c.gamma) and np.isnan(c.noise_dn)
    assert any("one frame" in f.what for f in c.findings)


def test_alignctl_analyze_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    names = []
    for k, f in enumerate(_top_frames(2.2, n=8)):
        p = tmp_path / f"still_{k}.png"
        cv2.imwrite(str(p), f)
        names.append(str(p))
    assert alignctl_main(["analyze", "camera", *names, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out.strip())
    assert obj["files"] == names and obj["frames"] == 8 and obj["bits"] == 8
    assert abs(obj["gamma"] - 2.2) <= 3 * obj["gamma_u"]
    assert any(f["level"] == "act" and "tone curve" in f["what"] for f in obj["findings"])
    assert alignctl_main(["analyze", "camera", *names]) == 0
    out = capsys.readouterr().out
    assert "8 frame(s) of 1280 x 720 px, 8-bit" in out and "[act] the camera applies" in out
    # an unreadable frame: exit code 2 and the reason, nothing measured
    (tmp_path / "junk.png").write_text("not an image")
    assert alignctl_main(["analyze", "camera", names[0], str(tmp_path / "junk.png"),
                          "--json"]) == 2
    captured = capsys.readouterr()
    assert "cannot read image" in captured.err
    assert "error" in json.loads(captured.out.strip())


def test_noise_that_does_not_change_with_the_level_is_not_told() -> None:
    """Read noise alone (our simulated rig's camera): a linear camera's read noise and a
    gamma 2 camera's shot noise look alike, so the range the noise allows holds both and
    no verdict is given, whichever end the best fit lands on."""
    w = posed_world(seed=1)
    opts = RenderOptions(read_noise_dn=2.0, electrons_per_dn=0.0)
    rng = np.random.default_rng(8)
    c = check_frames([render_top(w.top_scene(), w.top_camera, opts, rng) for _ in range(8)])
    lo, hi = c.gamma_range
    assert lo <= 1.0 and hi >= 2.0
    curve = [f for f in c.findings if f.key == "gamma"]
    assert len(curve) == 1 and curve[0].level == "note" and "not told apart" in curve[0].what
    assert f"gamma {lo:.1f}-{hi:.1f}" in curve[0].what


def _lag1_of_filtered_white_noise(amount: float, radius: float) -> float:
    """The correlation of neighbouring pixels (along a row) of white noise after an
    unsharp mask: sum k(x, y) k(x + 1, y) / sum k^2 over the filter's kernel k (its
    impulse response, from the same OpenCV blur the frames went through)."""
    d = np.zeros((31, 31), np.float32)
    d[15, 15] = 1.0
    k = (1 + amount) * d - amount * cv2.GaussianBlur(d, (0, 0), radius)
    k = k.astype(float)
    return float((k[:, 1:] * k[:, :-1]).sum() / (k * k).sum())


@pytest.mark.parametrize("amount,radius", [(0.5, 0.8), (1.0, 1.0), (2.0, 1.5)])
def test_the_noise_correlation_is_the_filters_own(amount: float, radius: float) -> None:
    """Sharpened frames: the correlation the check reads is the one the filter's kernel
    gives white noise (within 0.003: the estimator, the rounding's white share taken off,
    checked against the kernel's arithmetic)."""
    expected = _lag1_of_filtered_white_noise(amount, radius)
    c = check_frames([_sharpen(f, amount, radius) for f in _top_frames(1.0)])
    assert c.noise_correlation[0] == pytest.approx(expected, abs=0.003)
    assert c.noise_correlation[1] == pytest.approx(expected, abs=0.003)
    assert any(f.key == "sharpened" and f.level == "act" for f in c.findings)


def test_alignctl_analyze_camera_reads_12_bit_frames(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    """A 12-bit camera's frames saved as 16-bit PNGs (the corpus's 12-bit side view, seed
    5, index 4): read at 12 bits, and its gamma 2.2 curve found."""
    names = []
    for k, f in enumerate(_side_frames(2.2, 4)):
        assert f.dtype == np.uint16
        p = tmp_path / f"side_{k}.png"
        cv2.imwrite(str(p), f)
        names.append(str(p))
    assert alignctl_main(["analyze", "camera", *names, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out.strip())
    assert obj["bits"] == 12 and obj["jpeg_quality"] is None
    assert obj["gamma"] == pytest.approx(2.2, abs=0.1)
    assert any(f["key"] == "gamma" and f["level"] == "act" for f in obj["findings"])


def test_alignctl_analyze_camera_holds_the_frames_against_a_config(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """With --config, a camera whose frames say gamma 2.2 against a config that says 1
    (the reference sim config) gets an act line naming the key; with the config at 2.2,
    none."""
    import yaml

    names = []
    for k, f in enumerate(_side_frames(2.2, 2)):  # an uneven-light view, 8-bit
        p = tmp_path / f"side_{k}.png"
        cv2.imwrite(str(p), f)
        names.append(str(p))
    cfg = Path("configs/sim.yaml")
    assert alignctl_main(["analyze", "camera", *names, "--json", "--config", str(cfg),
                          "--role", "side"]) == 0
    obj = json.loads(capsys.readouterr().out.strip())
    said = [f for f in obj["findings"] if f["key"] == "config_gamma"]
    assert len(said) == 1 and said[0]["level"] == "act"
    assert "says gamma 1 for the side camera" in said[0]["what"]
    assert "cameras[side].gamma" in said[0]["advice"]
    data = yaml.safe_load(cfg.read_text())
    for cam in data["cameras"]:
        cam["gamma"] = 2.2
    other = tmp_path / "gamma.yaml"
    other.write_text(yaml.safe_dump(data))
    assert alignctl_main(["analyze", "camera", *names, "--json", "--config", str(other),
                          "--role", "side"]) == 0
    obj = json.loads(capsys.readouterr().out.strip())
    assert not [f for f in obj["findings"] if f["key"] == "config_gamma"]
