"""The model's own error in the likelihood (``calibration.inference.likelihood.model_error``): the draw and
grid terms recovered on a toy whose errors are known, bad input refused before any run, failed
runs never taken as a zero term, and the terms of a real run (the tiny S4 collapse)."""

import math

import numpy as np
import pytest
from helpers import placeholder_objective, tiny_s4

from calibration.inference.likelihood import ModelError, model_error

BLOCKS = {"profile": slice(0, 40), "front": slice(40, 240)}
DRAW = {"profile": 0.03, "front": 0.01}  # a residual's sd over particle draws
SHIFT = {"profile": 0.02, "front": 0.0}  # r(ρ dx) − r(dx), every row of the block
SCALE = np.r_[np.full(40, 2.0), np.full(200, 0.5)]  # row scales: the terms are in the blocks' relative units


class ToyObjective:
    """Residuals whose draw scatter and grid change are known: row i of block b at seed s on a
    grid ``level`` times coarsened is SCALE_i (base_i + level SHIFT_b + DRAW_b n_{s,i})."""

    keys = ("a",)
    blocks = BLOCKS
    row_scale = SCALE
    sampling_seed = 0

    def __init__(self, level=0, seeded=True, status=0):
        self.level, self.seeded, self.status, self.runs, self.dx = level, seeded, status, 0, 0.01 * 1.5**level
        self.base = np.linspace(-0.1, 0.1, 240)

    def _rows(self, seed):
        self.runs += 1
        n = np.random.default_rng(1000 * self.level + seed).standard_normal(240)
        shift = np.r_[np.full(40, SHIFT["profile"]), np.full(200, SHIFT["front"])]
        draw = np.r_[np.full(40, DRAW["profile"]), np.full(200, DRAW["front"])]
        r = SCALE * (self.base + self.level * shift + draw * n)
        return r, {"status": self.status if self.level else 0}

    def residuals(self, theta):
        return self._rows(0)

    def residuals_resampled(self, theta, seed):
        return self._rows(seed)

    def coarsened(self, ratio):
        self.coarse = ToyObjective(self.level + 1, self.seeded, self.status)
        return self.coarse

    def check_thetas(self, thetas, name="thetas"):
        if np.any(np.asarray(thetas) < 0):
            raise ValueError(f"{name}: a < 0")


def test_the_draw_and_grid_terms_of_known_errors():
    toy = ToyObjective()
    error = model_error(toy, {"a": 1.0}, draws=400, coarse_draws=400)
    assert error.draws == 401 and error.coarse_draws == 400 and toy.runs == 401 and toy.coarse.runs == 400
    for b in BLOCKS:  # 400 draws: the sd to ~4 %
        assert error.draw[b] == pytest.approx(DRAW[b], rel=0.1)
    # Richardson for order 1 and ρ = 1.5: the fine grid's error is the change over ρ − 1 = 0.5.
    assert error.grid["profile"] == pytest.approx(SHIFT["profile"] / 0.5, rel=0.1)
    # No grid change: the draws' share E = v (1/401 + 1/400) of mean (F̄ − C̄)² is taken off.
    # Left in, (0.5 grid)² would read E itself, a grid error that is not there; taken off, what
    # is left is the mean's fluctuation, E sqrt(2/200) = 0.1 E for 200 rows (5 of them here).
    expected = DRAW["front"] ** 2 * (1 / 401 + 1 / 400)
    assert (0.5 * error.grid["front"]) ** 2 < 0.5 * expected
    order2 = model_error(ToyObjective(), [1.0], draws=400, coarse_draws=400, order=2.0)
    assert order2.grid["profile"] == pytest.approx(error.grid["profile"] * 0.5 / 1.25, rel=1e-9)


def test_noise_adds_the_terms_in_quadrature():
    error = ModelError({"p": 0.03, "f": 0.0}, {"p": 0.04, "f": 0.1}, 5, 2, 1.5, 1.0, 0.01, 1.0)
    assert error.total() == {"p": pytest.approx(0.05), "f": pytest.approx(0.1)}
    assert error.noise(0.0) == error.total()
    assert error.noise({"p": 0.12, "f": 0.0}) == {"p": pytest.approx(0.13), "f": pytest.approx(0.1)}
    with pytest.raises(ValueError, match=r"data: no noise level for the block\(s\) \['f'\]"):
        error.noise({"p": 0.02})
    record = error.to_dict()
    assert record["total"]["p"] == pytest.approx(0.05) and record["order_assumed"] == 1.0


@pytest.mark.parametrize("kwargs, message", [
    ({"draws": 1}, "draws must be >= 2"),
    ({"draws": 2.0}, "draws must be an integer"),
    ({"coarse_draws": 0}, "coarse_draws must be >= 1"),
    ({"ratio": 1.0}, "ratio must be a finite factor > 1"),
    ({"ratio": math.nan}, "ratio must be a finite factor > 1"),
    ({"order": 0.0}, "order must be > 0"),
    ({"theta": {"b": 1.0}}, r"theta: no value for the key\(s\) \['a'\]"),
    ({"theta": [1.0, 2.0]}, "theta must be 1 finite values"),
    ({"theta": [math.inf]}, "theta must be 1 finite values"),
    ({"theta": [-1.0]}, "theta: a < 0"),
])
def test_bad_input_is_refused_before_any_run(kwargs, message):
    toy = ToyObjective()
    theta = kwargs.pop("theta", [1.0])
    with pytest.raises(ValueError, match=message):
        model_error(toy, theta, **kwargs)
    assert toy.runs == 0


def test_unmeasured_terms_are_refused_not_taken_as_zero():
    lattice = ToyObjective(seeded=False)
    with pytest.raises(ValueError, match="objective: its particles cannot be drawn again"):
        model_error(lattice, [1.0])
    assert lattice.runs == 0
    with pytest.raises(ValueError, match="no run on the grid 1.5 times coarser ran without status bits"):
        model_error(ToyObjective(status=4), [1.0])


# 11 s: three runs and a coarse one of the tiny S4; the terms' arithmetic is checked on a toy objective
# in the default suite.
@pytest.mark.slow
def test_the_terms_of_a_real_run():
    """The tiny S4 collapse (dx = L/6): the final profile's draw and grid terms are measured,
    finite and of the size its particles make (a few per cent of the peak, not zero)."""
    scene = tiny_s4()
    objective = placeholder_objective(scene, ("beta", "mu1"), xs=np.linspace(0.0, 0.16, 17))
    error = model_error(objective, {"beta": 0.25, "mu1": 0.38}, draws=2, coarse_draws=1)
    assert error.draws == 3 and error.coarse_draws == 1 and error.dx == pytest.approx(objective.dx)
    assert set(error.draw) == set(objective.blocks)
    for b in objective.blocks:
        assert 1e-3 < error.draw[b] < 0.3 and 1e-3 < error.grid[b] < 1.0
    again = model_error(objective, {"beta": 0.25, "mu1": 0.38}, draws=2, coarse_draws=1)
    assert again.draw == error.draw and again.grid == error.grid  # the draws are seeded: reproducible
