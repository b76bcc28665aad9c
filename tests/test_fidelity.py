"""The resolution study's analysis (jaxmpm.studies.fidelity.analyse_resolution) on hand-made rows: the
converged answer is the seed mean of the last setting, errors are relative to it, the cheapest
setting within a level is the one with the fewest particle-steps whose every error is inside it,
and the seed spread is (max − min) / mean."""

import numpy as np
import pytest

from jaxmpm.studies.fidelity import analyse_resolution

XS = 641  # the study's profile length


def _row(dx, ppc, sampling, seed, left, right, top, steps, h=1.0):
    return {"scene": "gates-collapse", "dx": dx, "ppc": ppc, "sampling": sampling, "seed": seed,
            "n_particles": int(steps / 100), "particle_steps": steps, "run_s": 1.0, "status": 0,
            "left": left, "right": right, "top": top, "profile": np.full(XS, h)}


def test_analysis_of_a_small_matrix():
    rows = [
        _row(0.004, 2, "lattice", 0, 0.090, 0.090, 0.030, 1e6, h=0.9),  # 10 % off: within no level
        _row(0.003, 3, "jitter", 0, 0.099, 0.1015, 0.0301, 5e6, h=0.99),  # within 2 %
        _row(0.003, 3, "jitter", 1, 0.1005, 0.0985, 0.0299, 5e6, h=1.01),
        _row(0.002, 3, "jitter", 0, 0.1002, 0.0999, 0.0300, 2e7, h=1.001),  # within 1 %
        _row(0.001, 3, "jitter", 1, 0.1010, 0.0990, 0.0300, 1e8),
        _row(0.001, 3, "jitter", 0, 0.0990, 0.1010, 0.0300, 1e8),
    ]
    out = analyse_resolution(rows)["scenes"]["gates-collapse"]
    ref = out["reference"]
    assert ref["seeds"] == [1, 0] and ref["left"] == pytest.approx(0.1) and ref["right"] == pytest.approx(0.1)
    first = out["runs"][0]["error"]
    assert first["left"] == pytest.approx(-0.1) and first["profile"] == pytest.approx(0.1)
    for level in ("5%", "2%"):  # the cheaper lattice run is 10 % off
        assert out["cheapest"][level]["dx"] == 0.003 and out["cheapest"][level]["seed"] == 0
    assert out["cheapest"]["1%"]["dx"] == 0.002
    spread = {s["dx"]: s for s in out["seed_spread"]}
    assert spread[0.003]["right"] == pytest.approx((0.1015 - 0.0985) / 0.1)
    assert spread[0.001]["left"] == pytest.approx(0.02)
    assert out["reference_uncertainty"]["left"] == pytest.approx(0.002)  # the 2 mm run, its finest neighbour


@pytest.mark.slow
def test_s2_with_the_reference_codes_sampling_agrees_with_it_at_its_resolution():
    """S2 at dx = 3 mm with the reference code's own sampling (Poisson disk, about 6 per cell;
    the mean of three seeds, as its one sample carries 1-3 % of noise) lies within 3 % of the
    reference code's dx = 2.98 mm row at that sampling on the left and right runouts and the
    top (docs/validation.md section 1)."""
    from jaxmpm.studies.fidelity import REFERENCE_S2, run_case

    rows = [run_case("gates-collapse", 0.003, 2.45, "poisson", seed) for seed in (0, 1, 2)]
    assert all(r["status"] == 0 for r in rows)
    for key, ref in REFERENCE_S2[2.98e-3, 6].items():
        mean = np.mean([r[key] for r in rows])
        assert abs(mean / ref - 1.0) < 0.03, (key, mean, ref)


@pytest.mark.slow
def test_s2_defaults_at_3mm_within_3_percent_of_the_reference_code():
    """The issue's criterion, ``run gates-collapse --dx 0.003`` with every other default
    (jittered 4 × 4: 16 particles per cell, seed 0), against the reference code's dx = 2.98 mm
    row at 16 per cell: within 3 % on the left and right runouts and the top
    (docs/validation.md section 1; measured +1.6, +2.5 and -0.1 %)."""
    from jaxmpm.scenes import build_scene
    from jaxmpm.studies.fidelity import REFERENCE_S2, run_case

    info = build_scene("gates-collapse", dx=0.003).info
    assert (info.ppc, info.sampling) == (4, "jitter")  # 16 per cell, as the reference row
    row = run_case("gates-collapse", 0.003, info.ppc, info.sampling, 0)
    assert row["status"] == 0
    for key, ref in REFERENCE_S2[2.98e-3, 16].items():
        assert abs(row[key] / ref - 1.0) < 0.03, (key, row[key], ref)
