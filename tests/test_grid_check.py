"""The grid's share of a fit's interval: ``Scene.at_dx``, ``Objective.at_dx``, ``grid_shift``."""

import dataclasses
import math

import numpy as np
import pytest

from calibration import Objective, ProfileTarget, fit
from calibration.inference.gauss_newton import gauss_newton_uncertainty
from calibration.inference.gridcheck import GCI_SAFETY, GRID_ORDER, grid_shift
from jaxmpm import scenes

L = 0.089
KEYS = ("beta", "mu1")


def test_scene_at_dx_is_the_scene_built_at_that_dx_with_its_current_params():
    scene = scenes.cohesive_collapse(dx=L / 6, t_end=0.1, beta=0.2, pc0=400.0)
    later = dataclasses.replace(scene, params=scene.params.replace(mu1=0.41))  # set after building
    coarse = later.at_dx(L / 4)
    built = scenes.cohesive_collapse(dx=L / 4, t_end=0.1, beta=0.2, pc0=400.0)
    assert coarse.config == built.config and coarse.info == built.info
    np.testing.assert_array_equal(np.asarray(coarse.state.x), np.asarray(built.state.x))
    assert float(coarse.params.mu1) == 0.41 and float(coarse.params.pc0) == 400.0
    np.testing.assert_array_equal(np.asarray(coarse.resampled(3).x), np.asarray(built.resampled(3).x))
    aspect = scenes.aspect_ratio_collapse(a=2.0, dx=0.01, t_end=0.1).at_dx(0.0125)
    assert aspect.info.aspect == 2.0 and aspect.config.grid.dx == 0.0125
    with pytest.raises(ValueError, match="dx must be a positive number"):
        scene.at_dx(-1.0)
    with pytest.raises(ValueError, match="cannot be rebuilt"):
        dataclasses.replace(scene, remake=None).at_dx(L / 4)


class _Linear:
    """An objective whose coarse residual at θ is J a exactly: the shift must be −a."""

    seeded = False  # no seeded sampling: the scene's own draw only

    def __init__(self, J, a, dx=0.01):
        self.J, self.a, self.dx = np.asarray(J, float), np.asarray(a, float), dx
        self.asked = []

    def coarsened(self, ratio):
        self.asked.append(ratio * self.dx)
        coarse = _Linear(self.J, self.a, ratio * self.dx)
        coarse.residuals = lambda theta: (self.J @ self.a, {"status": np.int32(0)})
        return coarse


def test_grid_shift_is_the_gauss_newton_step_to_the_coarse_minimum_and_its_gci():
    rng = np.random.default_rng(0)
    J, a = rng.standard_normal((30, 2)), np.array([0.02, -0.05])
    objective = _Linear(J, a)
    grid = grid_shift(objective, np.array([0.3, 0.4]), J, ratio=1.5, draws=3)
    assert objective.asked == [pytest.approx(0.015)]
    np.testing.assert_allclose(grid.shift, -a, rtol=1e-12)
    np.testing.assert_allclose(grid.halfwidth, GCI_SAFETY * np.abs(a) / (1.5 ** GRID_ORDER - 1.0), rtol=1e-12)
    assert grid.draws == 1  # no seeded sampling: the scene's own draw only
    # Rank one along the shift, with the grid's standard errors' total length.
    assert np.linalg.matrix_rank(grid.cov) == 1
    np.testing.assert_allclose(np.trace(grid.cov), np.sum(grid.stderr ** 2), rtol=1e-12)
    # The interval carries it, and says the fit is not converged where it dominates.
    r = np.zeros(30)
    blocks = {"profile": slice(0, 30)}
    unc = gauss_newton_uncertainty(J, r, KEYS, np.array([0.3, 0.4]), blocks, np.ones(30), noise=1e-4, grid=grid)
    assert unc.grid_converged is False and "Not converged in the grid" in unc.statement
    np.testing.assert_allclose(unc.stderr ** 2, unc.stderr_statistical ** 2 + grid.stderr ** 2, rtol=1e-9)
    d = unc.to_dict()
    assert d["grid_converged"] is False and set(d["stderr_grid"]) == set(KEYS) and d["grid"]["ratio"] == 1.5
    small = grid_shift(_Linear(J, 1e-9 * a), np.array([0.3, 0.4]), J)
    unc = gauss_newton_uncertainty(J, r, KEYS, np.array([0.3, 0.4]), blocks, np.ones(30), noise=1e-2, grid=small)
    assert unc.grid_converged is True and "Converged in the grid" in unc.statement


class _Graded(_Linear):
    """An objective whose fit at grid spacing h would move θ by c ((h/dx)^p − 1): a grid error of
    order p, as the coarse residual J a(h) with a(h) = −c ((h/dx)^p − 1) (``p=None``: a move of
    +c at ρ dx and −c/2 at ρ² dx, alternating in sign)."""

    def __init__(self, J, c, p, dx=0.01):
        super().__init__(J, np.zeros_like(np.asarray(c, float)), dx)
        self.c, self.p = np.asarray(c, float), p

    def coarsened(self, ratio):
        self.asked.append(ratio * self.dx)
        h = ratio * self.dx
        if self.p is None:
            a = -self.c * (1.0 if ratio < 1.6 else -0.5)  # +c at ρ, −c/2 at ρ²: oscillating
        else:
            a = -self.c * ((h / self.dx) ** self.p - 1.0)
        coarse = _Linear(self.J, a, h)
        coarse.residuals = lambda theta: (self.J @ a, {"status": np.int32(0)})
        return coarse


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_three_grids_show_the_order_and_give_roaches_index(p):
    rng = np.random.default_rng(1)
    J, c = rng.standard_normal((30, 2)), np.array([0.02, -0.05])
    objective = _Graded(J, c, p)
    grid = grid_shift(objective, np.array([0.3, 0.4]), J, ratio=1.5, levels=2)
    assert objective.asked == [pytest.approx(0.015), pytest.approx(0.0225)]
    assert grid.order == pytest.approx(p, rel=1e-9)
    np.testing.assert_allclose(grid.shift, c * (1.5 ** p - 1), rtol=1e-12)
    np.testing.assert_allclose(grid.halfwidth, 1.25 * np.abs(grid.shift) / (1.5 ** p - 1), rtol=1e-9)
    d = grid.to_dict(KEYS)
    assert d["levels"] == 2 and d["order_observed"] == pytest.approx(p) and "observed order" in d["method"]


def test_oscillating_grids_widen_the_index():
    rng = np.random.default_rng(2)
    J, c = rng.standard_normal((30, 2)), np.array([0.02, -0.05])
    grid = grid_shift(_Graded(J, c, None), np.array([0.3, 0.4]), J, ratio=1.5, levels=2)
    assert grid.order is None and "oscillate" in grid.method
    e21, e32 = grid.shift, grid.shift2 - grid.shift
    np.testing.assert_allclose(grid.halfwidth, GCI_SAFETY * np.maximum(abs(e21), abs(e32)) / 0.5, rtol=1e-12)
    assert np.all(grid.halfwidth > GCI_SAFETY * np.abs(e21) / 0.5)  # wider than one coarser grid would say
    with pytest.raises(ValueError, match="grid_levels must be 1 or 2"):
        grid_shift(_Graded(J, c, 1.0), np.array([0.3, 0.4]), J, levels=3)


@pytest.mark.parametrize("ratio, draws, match", [(1.0, 2, "grid_ratio"), (0.5, 2, "grid_ratio"),
                                                 (math.nan, 2, "grid_ratio"), (1.5, 0, "grid_draws")])
def test_bad_grid_options_are_refused_before_anything_runs(ratio, draws, match, monkeypatch):
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.05)
    xs = np.linspace(0.0, 0.15, 9)
    objective = Objective(scene, KEYS, profile=ProfileTarget(xs, np.ones_like(xs)), check_data=False)

    def tripwire(*args, **kwargs):
        raise AssertionError("the model ran: the options should have been refused before")

    monkeypatch.setattr(Objective, "residuals_and_jacobian", tripwire)
    monkeypatch.setattr(Objective, "residuals_and_jacobian_z", tripwire)
    with pytest.raises(ValueError, match=match):
        fit(objective, {"beta": 0.1}, grid_ratio=ratio, grid_draws=draws)


@pytest.mark.slow  # 23 s: two draws rebuilt coarser and compiled; the grid term of a fit runs by default in
# tests/test_calibration_cli.py (the documented JSON) and the shift's algebra in the test above
def test_grid_shift_runs_the_objective_rebuilt_coarser_over_two_draws():
    """On a real objective: the shift is −J⁺ of the mean residual of the objective rebuilt at
    1.5 dx over two particle draws (any J: the shift is linear in that mean)."""
    scene = scenes.cohesive_collapse(dx=L / 4, t_end=0.05, beta=0.25)
    xs = np.linspace(0.0, 0.14, 15)
    objective = Objective(scene, KEYS, profile=ProfileTarget(xs, 0.05 * np.ones_like(xs)), check_data=False)
    theta = np.array([0.25, 0.4])
    J = np.random.default_rng(2).standard_normal((xs.size, 2))
    grid = grid_shift(objective, theta, J)
    coarse = objective.at_dx(1.5 * L / 4)
    assert coarse.keys == objective.keys and coarse.scene.config.grid.dx == pytest.approx(1.5 * L / 4)
    assert coarse.sigma == pytest.approx(1.5 * objective.sigma)  # not given: follows the new particle spacing
    r_c = np.mean([np.asarray(coarse.residuals_resampled(theta, s)[0]) for s in (0, 1)], axis=0)
    np.testing.assert_allclose(grid.shift, -np.linalg.lstsq(J, r_c, rcond=None)[0], rtol=1e-6, atol=1e-12)
    assert grid.draws == 2 and grid.dx == pytest.approx(L / 4)
    # A fit's grid term through the command line: tests/test_calibration_cli.py (the documented JSON).


def test_intervals_are_the_sandwich_of_the_fit_as_weighted():
    """Two blocks of unequal length, each weighed as a whole (row_scale² = 1/m_b): the interval is
    A⁻¹BA⁻¹, wider than (Σ J_bᵀJ_b/σ²)⁻¹; with one block the two agree."""
    rng = np.random.default_rng(4)
    Je = rng.standard_normal((21, 2))  # relative units: 20 profile rows, 1 front row
    blocks = {"profile": slice(0, 20), "front": slice(20, 21)}
    row_scale = np.concatenate([np.full(20, np.sqrt(1 / 20)), np.ones(1)])
    J, r, sigma = Je * row_scale[:, None], np.zeros(21), 0.02
    unc = gauss_newton_uncertainty(J, r, KEYS, np.array([0.3, 0.4]), blocks, row_scale, noise=sigma)
    w = row_scale ** 2
    A = Je.T @ (w[:, None] * Je)
    B = Je.T @ ((w * w)[:, None] * Je) * sigma ** 2
    sandwich = np.linalg.inv(A) @ B @ np.linalg.inv(A)
    np.testing.assert_allclose(unc.cov, sandwich, rtol=1e-8)
    assert np.all(np.diag(unc.cov) > np.diag(np.linalg.inv(Je.T @ Je / sigma ** 2)))
    one = gauss_newton_uncertainty(J[:20], r[:20], KEYS, np.array([0.3, 0.4]), {"profile": slice(0, 20)},
                                   row_scale[:20], noise=sigma)
    np.testing.assert_allclose(one.cov, np.linalg.inv(Je[:20].T @ Je[:20] / sigma ** 2), rtol=1e-8)


def test_the_three_grid_order_does_not_depend_on_the_keys_units():
    """A key in large units (ξ ~ 50 beside μ ~ 0.4) must not decide the order alone: with the
    shifts measured in each key's scale, changing a key's units (its shifts and scale together)
    leaves the order and the index in those units unchanged. Here μ2 converges with order 2 and
    ξ oscillates by about one of its sds: measured in raw units ξ alone says "oscillate"."""
    from calibration.inference.gridcheck import three_grid_index

    shift1 = np.array([-0.10, -3.4])
    shift2 = shift1 + np.array([-0.225, 28.0])  # e32: mu2 1.5^2 times e21, xi the other way
    scale = np.array([0.03, 5.0])
    base = three_grid_index(shift1, shift2, 1.5, scale)
    assert base[1] == pytest.approx(1.49, abs=0.01) and "converging" in base[2]
    units = np.array([1.0, 100.0])  # xi in other units
    other = three_grid_index(shift1 * units, shift2 * units, 1.5, scale * units)
    assert other[1] == pytest.approx(base[1], rel=1e-12) and other[2] == base[2]
    np.testing.assert_allclose(other[0], base[0] * units, rtol=1e-12)
    assert three_grid_index(shift1, shift2, 1.5)[1] is None  # unscaled: xi's units decide
    with pytest.raises(ValueError, match="scale must be positive"):
        three_grid_index(shift1, shift2, 1.5, [0.03, 0.0])
