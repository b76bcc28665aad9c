"""The validation studies of docs/validation.md as assertions. Slow (minutes each): run with
``python -m pytest -m slow``."""

import pytest

from jaxmpm.studies.validation import run_study

pytestmark = pytest.mark.slow


def test_cohesion_shortens_runout_and_keeps_the_top_standing():
    runs = {r["beta"]: r for r in run_study("cohesion")["runs"]}
    assert all(r["status"] == 0 for r in runs.values())
    assert runs[0.25]["runout"] < 0.75 * runs[0.0]["runout"]
    assert runs[0.25]["final_height"] > 0.9 * 0.089 > runs[0.0]["final_height"]


def test_convergence_profile_difference_falls_with_dx_and_the_front_from_10mm_down():
    """S3 at 10° at the scene defaults (docs/validation.md section 3): the deposit profile moves
    towards the finest run at every refinement; the front read from it does so from 10 mm down
    (at 20 mm, seven cells across the column, it lies 2 cm short, and 10 mm 3 cm short: not
    monotone there)."""
    out = run_study("convergence")
    assert all(r["status"] == 0 for r in out["runs"])
    coarse = out["runs"][:-1]
    profiles = [r["profile_l2_rel"] for r in coarse]
    assert profiles == sorted(profiles, reverse=True), profiles
    assert coarse[-1]["front_diff"] < 0.5 * coarse[-2]["front_diff"], coarse


@pytest.fixture(scope="module")
def bagnold():
    # The slopes the checks below read; the study's default adds 28° (docs/validation.md), a quarter
    # of its cost that no check here reads.
    return run_study("bagnold", slopes=(22.0, 24.0, 26.0))


def test_bagnold_surface_velocity_within_3_percent_and_better_than_coarse(bagnold):
    """The issue's criterion on the surface velocity at 22°, 24° and 26° (docs/validation.md
    section 2): within 3 % at the finest dx, and smaller there than at the coarsest."""
    for slope in (22.0, 24.0, 26.0):
        rows = sorted((c for c in bagnold["all_cases"] if c["slope_deg"] == slope), key=lambda c: -c["dx"])
        assert all(c["status"] == 0 for c in rows)
        assert abs(rows[-1]["rel_error"]) < 0.03, rows[-1]
        assert abs(rows[-1]["rel_error"]) < abs(rows[0]["rel_error"]), rows


@pytest.mark.parametrize("slope", [22.0, 24.0, pytest.param(26.0, marks=pytest.mark.xfail(
    strict=True, reason="the particle rows start to cluster at 26 deg and h/32 even in float64 (top row at 0.93 h0): "
    "profile error 3.4 % (docs/validation.md section 2)"))])
def test_bagnold_velocity_profile_within_3_percent(bagnold, slope):
    """In float64 (as the tests run) at h/32: 1.6 % at 22°, 1.4 % at 24°; 3.4 % at 26° (the strict
    xfail). In float32 (the CLI default) the particles cluster in fast shear at 24-28° and the
    profile is off by 11-23 % (docs/validation.md)."""
    case = next(c for c in bagnold["cases"] if c["slope_deg"] == slope)
    assert case["profile_rel_error"] < 0.03, case


def test_avalanche_study_quick():
    """``validate avalanche --quick`` (docs/avalanche.md, about 4 minutes): every run is clean; the
    runout moves by under 1 % of the travel from dx = 2 to 1 m; the obstacle stops the snow
    short of the open path's runout and carries a force; the default dry snow keeps its volume
    (median J within 0.8–1.5), which without hardening (ξ = 0) it does not."""
    out = run_study("avalanche", quick=True)
    runs = {r["case"]: r for r in out["runs"]}
    assert all(r["status"] == 0 for r in runs.values()), runs
    assert out["runout_change_finest_pair"] < 0.01
    open_path, obstacle = runs["dry, dx = 2 m"], runs["dry, 5 m obstacle at x = 3800 m"]
    assert obstacle["runout_x"] < open_path["runout_x"] and obstacle["obstacle_force_max_kn_per_m"] > 0
    assert 0.8 < open_path["volume_ratio_percentiles"]["p50"] < 1.5
    assert runs["dry, xi = 0 (no hardening)"]["volume_ratio_percentiles"]["p50"] > 1.5
