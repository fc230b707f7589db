"""The decision rule (guarded / simple acceptance), the uncertainty budget's arithmetic and
the centre pool's sweep-to-sweep excess: the numbers an operator's verdict rests on."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from alignd.procedures.budget import Budget, Contribution
from alignd.procedures.decision import decide
from alignd.procedures.sweep import CentrePool


def test_guarded_acceptance_zones_per_iso_14253_1() -> None:
    ok = decide(2.1, 3.4, 10.0)
    assert ok.outcome == "conforms" and ok.guard_band_um == pytest.approx(3.4)
    assert ok.accept_below_um == pytest.approx(6.6) and ok.reject_above_um == pytest.approx(13.4)
    assert ok.text().startswith("within 10 um: offset 2.1 um, U 3.4 um (k=2), guard band 3.4 um")
    assert "ISO 14253-1" in ok.text()
    # the edges: accept up to T - U inclusive, reject from T + U
    assert decide(6.6, 3.4, 10.0).outcome == "conforms"
    assert decide(6.7, 3.4, 10.0).outcome == "undecided"
    assert decide(13.3, 3.4, 10.0).outcome == "undecided"
    assert decide(13.4, 3.4, 10.0).outcome == "does_not_conform"
    assert decide(13.4, 3.4, 10.0).text().startswith("beyond 10 um")
    assert decide(8.0, 3.4, 10.0).margin_um == pytest.approx(-1.4)


def test_simple_acceptance_decides_on_the_measured_value_alone() -> None:
    assert decide(9.9, 5.0, 10.0, "simple").outcome == "conforms"
    assert decide(10.1, 0.1, 10.0, "simple").outcome == "does_not_conform"
    assert decide(9.9, 5.0, 10.0, "simple").guard_band_um == 0.0
    assert "no guard band" in decide(9.9, 5.0, 10.0, "simple").text()
    # a measurement as uncertain as the tolerance itself decides nothing
    assert decide(2.0, 10.5, 10.0, "simple").outcome == "undecided"
    with pytest.raises(ValueError, match="unknown decision rule 'lenient'"):
        decide(1.0, 1.0, 10.0, "lenient")  # type: ignore[arg-type]


def test_budget_adds_in_quadrature_with_k_2() -> None:
    b = Budget((Contribution("centre fit", 1.2, "A", ""),
                Contribution("target point", 0.5, "A", ""),
                Contribution("residual error motion", 1.0, "B", "")))
    assert b.combined_um == pytest.approx(math.sqrt(1.44 + 0.25 + 1.0))
    assert b.U_um == pytest.approx(2 * b.combined_um)
    assert b.get("target point") == 0.5 and b.get("stage repeatability") == 0.0
    assert b.lines()[-1].startswith("expanded U (k=2)")


def _pool(centres: np.ndarray, sigma: float) -> CentrePool:
    pool = CentrePool()
    for c in centres:
        pool.add(SimpleNamespace(center_px=c, cov_px2=sigma**2 * np.eye(2)))
    return pool


def test_pool_finds_no_excess_in_consistent_sweeps() -> None:
    rng = np.random.default_rng(4)
    p = _pool(rng.normal(0.0, 0.01, (6, 2)), 0.01).pooled()
    assert p.chi2 < 15.1  # below the 99 % point of chi2(10): no significant excess
    assert p.excess_px2 == 0.0
    assert np.sqrt(np.diag(p.cov_px2)) == pytest.approx([0.01 / math.sqrt(6)] * 2)


def test_pool_measures_the_scatter_the_fits_do_not_know() -> None:
    # ten sweeps whose centres scatter by 0.025 px while each fit claims 0.01 px
    rng = np.random.default_rng(5)
    p = _pool(rng.normal(0.0, 0.025, (10, 2)), 0.01).pooled()
    assert p.n_sweeps == 10  # none so far off that the axis would seem to have moved
    tau = math.sqrt(p.excess_px2)
    assert 0.012 < tau < 0.035  # the true excess: sqrt(0.025^2 - 0.01^2) = 0.023
    # the pooled uncertainty follows the scatter, not the fits' claim
    assert math.sqrt(p.cov_px2[0, 0]) == pytest.approx(math.sqrt((0.01**2 + tau**2) / 10))


def test_the_budget_names_how_far_the_centre_fit_was_widened() -> None:
    """A sweep whose fit was widened for corner errors that are not independent (its
    covariance twice the residuals' alone, alignd.solve.rigid) is pooled with it, and the
    factor (in sigma) is kept for the budget's basis."""
    pool = CentrePool()
    for c in ((0.0, 0.0), (0.01, -0.01)):
        pool.add(SimpleNamespace(center_px=np.array(c), cov_px2=2e-4 * np.eye(2),
                                 extra={"cov_independent_px2": 1e-4 * np.eye(2)}))
    assert pool.pooled().widened == pytest.approx(math.sqrt(2.0))
    plain = _pool(np.zeros((2, 2)), 0.01).pooled()
    assert plain.widened == pytest.approx(1.0)


def test_a_fits_corner_bias_is_not_averaged_down_by_more_sweeps() -> None:
    """The excess a fit adds for one corner's biased path repeats in every sweep over the
    same place: four such sweeps keep it whole, while their noise pools to a quarter."""
    pool = CentrePool()
    bias = 4e-4 * np.eye(2)
    for c in ((0.0, 0.0), (0.001, 0.0), (0.0, -0.001), (-0.001, 0.001)):
        pool.add(SimpleNamespace(center_px=np.array(c), cov_px2=1e-4 * np.eye(2) + bias,
                                 extra={"features_excess_px2": bias,
                                        "cov_independent_px2": 1e-4 * np.eye(2)}))
    p = pool.pooled()
    np.testing.assert_allclose(p.cov_px2, 0.25e-4 * np.eye(2) + bias, rtol=1e-9)
    assert p.widened == pytest.approx(math.sqrt(4.25e-4 / 0.25e-4))
