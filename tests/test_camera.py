"""Camera sources: replay folders and videos, HTTP snapshots, and their failures."""

from __future__ import annotations

import http.server
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.camera import OpenCVCamera, ReplayCamera, SnapshotCamera, open_camera
from drivers.errors import CameraError


def _image(i: int) -> np.ndarray:
    img = np.zeros((48, 64), np.uint8)
    img[10:20, 5 + i: 25 + i] = 200
    return img


def test_replay_folder_yields_images_in_name_order(tmp_path: Path) -> None:
    for i in (2, 0, 1):
        cv2.imwrite(str(tmp_path / f"frame_{i:03d}.png"), _image(i))
    cam = open_camera("top", str(tmp_path))
    assert isinstance(cam, ReplayCamera)
    with cam:
        frames = [cam.grab() for _ in range(3)]
        with pytest.raises(CameraError, match="replay exhausted"):
            cam.grab()
    for i, f in enumerate(frames):
        assert np.array_equal(f.image, _image(i))
        assert f.metadata["file"].endswith(f"frame_{i:03d}.png")
    assert [f.seq for f in frames] == [1, 2, 3]


def test_replay_of_missing_source_names_camera_and_path(tmp_path: Path) -> None:
    with pytest.raises(CameraError, match=r"does not exist.*device top.*nowhere"):
        ReplayCamera("top", str(tmp_path / "nowhere")).open()


def test_video_file_replays_its_frames(tmp_path: Path) -> None:
    path = str(tmp_path / "sweep.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    if not writer.isOpened():
        pytest.skip("no MJPG writer in this OpenCV build")
    for i in range(4):
        writer.write(cv2.cvtColor(_image(i), cv2.COLOR_GRAY2BGR))
    writer.release()
    with open_camera("top", path) as cam:
        f0 = cam.grab()
        f1 = cam.grab()
    assert f0.image.shape[:2] == (48, 64)
    assert f1.seq == f0.seq + 1
    # the bright bar moved one pixel right between frames (MJPG is lossy: compare centroids)
    cols = [np.average(np.arange(64), weights=f.gray.astype(float).sum(0)) for f in (f0, f1)]
    assert cols[1] - cols[0] == pytest.approx(1.0, abs=0.3)


def test_unopenable_device_is_a_clear_error() -> None:
    with pytest.raises(CameraError, match="cannot open camera source"):
        OpenCVCamera("top", "/dev/video-does-not-exist").open()


class _Snap(http.server.BaseHTTPRequestHandler):
    body = b""

    def do_GET(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "image/png")
        self.end_headers()
        self.wfile.write(self.body)

    def log_message(self, *args: object) -> None:
        pass


def test_snapshot_url_fetches_a_fresh_png_per_grab() -> None:
    ok, png = cv2.imencode(".png", _image(3))
    assert ok
    _Snap.body = png.tobytes()
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Snap)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        cam = open_camera("top", f"http://127.0.0.1:{srv.server_port}/snapshot.png")
        assert isinstance(cam, SnapshotCamera)
        t_move_done = time.monotonic()
        frame = cam.grab(after=t_move_done)
        assert frame.timestamp >= t_move_done
        assert np.array_equal(frame.image, _image(3))
        _Snap.body = b"not an image"
        with pytest.raises(CameraError, match="not a decodable"):
            cam.grab()
    finally:
        srv.shutdown()
        srv.server_close()


def test_snapshot_unreachable_names_the_url() -> None:
    with pytest.raises(CameraError, match=r"snapshot request failed.*127\.0\.0\.1:9"):
        SnapshotCamera("top", "http://127.0.0.1:9/snap.jpg").grab(timeout_s=0.5)
