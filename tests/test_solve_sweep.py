"""Sweep file contract: parsing, round trip, and errors that name the file and the key."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from alignd.errors import InputError
from alignd.solve import Sweep, load_sweep, parse_sweep, sweep_to_json


def _obj() -> dict:
    return {"version": 1, "pixel_size_um": 160.0, "frames": [
        {"angle_deg": -10.0, "features": [[1.0, 2.0], [3.0, 4.0], None]},
        {"angle_deg": 0.0, "features": [[1.5, 2.5], None, [5, 6]]},
        {"angle_deg": 10.0, "features": [[2.0, 3.0], [3.5, 4.5], [5.5, 6.5]]},
    ]}


def test_parse_shapes_and_nulls() -> None:
    sw = parse_sweep(_obj(), "s.json")
    assert sw.points.shape == (3, 3, 2)
    assert sw.angles_deg.tolist() == [-10.0, 0.0, 10.0]
    assert sw.pixel_size_um == 160.0
    assert np.isnan(sw.points[0, 2]).all() and np.isnan(sw.points[1, 1]).all()
    assert sw.points[1, 2].tolist() == [5.0, 6.0]


def test_round_trip_through_file(tmp_path) -> None:
    sw = parse_sweep(_obj(), "s.json")
    path = tmp_path / "s.json"
    path.write_text(json.dumps(sweep_to_json(sw)))
    back = load_sweep(path)
    np.testing.assert_array_equal(back.angles_deg, sw.angles_deg)
    np.testing.assert_array_equal(np.isnan(back.points), np.isnan(sw.points))
    np.testing.assert_array_equal(np.nan_to_num(back.points), np.nan_to_num(sw.points))
    assert sweep_to_json(back)["frames"][0]["features"][2] is None


def test_pixel_size_optional() -> None:
    obj = _obj()
    del obj["pixel_size_um"]
    assert parse_sweep(obj).pixel_size_um is None
    obj["pixel_size_um"] = None
    assert parse_sweep(obj).pixel_size_um is None


@pytest.mark.parametrize("mutate, fragment", [
    (lambda o: o.update(version=2), "unsupported version 2"),
    (lambda o: o.pop("version"), "missing key 'version'"),
    (lambda o: o.update(frames=[]), "'frames' must be a non-empty list"),
    (lambda o: o["frames"][1]["features"].pop(), "frames[1].features: ragged"),
    (lambda o: o["frames"][2].update(angle_deg=math.nan), "frames[2].angle_deg"),
    (lambda o: o["frames"][2].update(angle_deg="10"), "frames[2].angle_deg"),
    (lambda o: o["frames"][0]["features"].__setitem__(1, [1.0]), "frames[0].features[1]"),
    (lambda o: o["frames"][0]["features"].__setitem__(1, [1.0, math.inf]),
     "frames[0].features[1]"),
    (lambda o: o["frames"][0]["features"].__setitem__(1, [True, 2.0]), "frames[0].features[1]"),
    (lambda o: o.update(pixel_size_um=-1), "pixel_size_um"),
    (lambda o: o["frames"].__setitem__(0, [1, 2]), "frames[0]: expected an object"),
])
def test_parse_errors_name_source_and_key(mutate, fragment) -> None:
    obj = _obj()
    mutate(obj)
    with pytest.raises(InputError) as ei:
        parse_sweep(obj, "sweeps/a.json")
    msg = str(ei.value)
    assert msg.startswith("sweeps/a.json: ")
    assert fragment in msg


def test_top_level_not_object() -> None:
    with pytest.raises(InputError, match="expected a JSON object"):
        parse_sweep([1, 2], "x.json")


def test_load_bad_json_and_nan_literal(tmp_path) -> None:
    p = tmp_path / "bad.json"
    p.write_text('{"version": 1, "frames": [')
    with pytest.raises(InputError, match=r"bad\.json: bad JSON at line 1"):
        load_sweep(p)
    p.write_text('{"version": 1, "frames": [{"angle_deg": NaN, "features": [[1, 2]]}]}')
    with pytest.raises(InputError, match="NaN is not allowed"):
        load_sweep(p)
    with pytest.raises(InputError, match="cannot read sweep file"):
        load_sweep(tmp_path / "missing.json")


def test_sweep_properties() -> None:
    sw = Sweep(angles_deg=np.zeros(4), points=np.zeros((4, 3, 2)))
    assert (sw.n_frames, sw.n_features) == (4, 3)
