"""The validation studies of docs/validation.md as assertions. Slow (minutes each): run with
``python -m pytest -m slow``."""

import pytest

from jaxmpm.validate import run_study

pytestmark = pytest.mark.slow


def test_cohesion_shortens_runout_and_keeps_the_top_standing():
    runs = {r["beta"]: r for r in run_study("cohesion")["runs"]}
    assert all(r["status"] == 0 for r in runs.values())
    assert runs[0.25]["runout"] < 0.75 * runs[0.0]["runout"]
    assert runs[0.25]["final_height"] > 0.9 * 0.089 > runs[0.0]["final_height"]


def test_convergence_runout_difference_halves_from_10mm_down():
    out = run_study("convergence")
    base = [r for r in out["runs"] if r["ppc"] == 2]
    assert all(r["status"] == 0 for r in out["runs"])
    # Differences to the finest run fall as dx falls (docs/validation.md section 2).
    diffs = [r["runout_diff"] for r in base[:-1]]
    assert diffs == sorted(diffs, reverse=True)
    assert base[-2]["runout_diff"] <= 0.5 * base[-3]["runout_diff"]


@pytest.mark.xfail(strict=True, reason="docs/validation.md section 1: the surface velocity is 1-10 % off "
                   "and the particle layer collapses geometrically in rapid shear; open problem")
def test_bagnold_surface_velocity_within_3_percent():
    cases = run_study("bagnold")["cases"]
    for case in cases:
        if case["slope_deg"] in (22.0, 24.0, 26.0):
            assert abs(case["rel_error"]) < 0.03, case
