"""A velocity profile v(z) of the steady incline flow as a flow rule's model: the closed form
v(z) = U_s(h) − U_s(h − z) against Bagnold's profile (no walls) and ``side_wall_velocity``'s
quadrature (walls), its ends and its depth average, its derivatives against central differences
in float64 (finite at the bed and at the surface), and what it refuses."""

import math

import jax
import numpy as np
import pytest

from jaxmpm import SideWalls
from jaxmpm.params import DEFAULTS
from jaxmpm.scenes import S1_PARAMS, bagnold_velocity
from jaxmpm.scenes.incline import side_wall_velocity, steady_velocity

MATERIAL = {**DEFAULTS, **S1_PARAMS}
TRUTH = {k: MATERIAL[k] for k in ("mu1", "mu2", "I0")}
FIXED = {k: MATERIAL[k] for k in ("rho", "rho_s", "d")}
SHARES = np.array([0.0, 1e-4, 0.1, 0.5, 0.9, 0.999, 1.0])  # z / h, the bed and the surface included


def velocity(h, slope, quantity="profile", walls=None, mu_w=None, z=None, p=MATERIAL):
    return np.asarray(steady_velocity(h, slope, p["mu1"], p["mu2"], p["I0"], p["rho"], p["rho_s"], p["d"], quantity,
                                      walls, mu_w, height=z))


@pytest.mark.parametrize("slope", [21.5, 26.0, 32.0])
def test_without_walls_the_profile_is_bagnolds(slope):
    for h in (0.005, 0.038):
        z = SHARES * h
        v = velocity(h, slope, z=z)
        assert v[0] == 0.0 and np.all(np.diff(v) > 0)
        np.testing.assert_allclose(v, bagnold_velocity(z, h, slope, MATERIAL), rtol=1e-10, atol=0.0)


@pytest.mark.parametrize("width, slope", [(0.02, 22.0), (0.02, 28.0), (0.05, 25.0), (0.2, 22.0), (0.2, 30.0),
                                          (1.0, 26.0)])
def test_between_walls_the_profile_is_the_integral_of_the_shear_rate(width, slope):
    """Against ``side_wall_velocity``'s trapezoid, whose error, at the surface's sqrt(ζ) end, falls
    as N^-1.5: 3e-4 of the surface velocity at its default 4001 points where the flowing layer
    spans few of them (2 cm, 22°: ζ* = 1.5 mm), 2.3e-6 at 10^5 points, which this takes; the
    tolerance, 1e-5 of the surface velocity, is four times that. Below ζ* (a static base) both
    are 0."""
    walls, h = SideWalls(width, 0.3), 0.03
    z = SHARES * h
    v = velocity(h, slope, walls=walls, z=z)
    quadrature, stop = side_wall_velocity(z, h, slope, MATERIAL, walls, points=100_001)
    np.testing.assert_allclose(v, quadrature, rtol=0.0, atol=1e-5 * v[-1])
    static = h - z > stop
    assert np.all(v[static] == 0.0) and np.all(v[~static][1:] > 0)
    assert (width, slope) != (0.02, 22.0) or static.sum() == 5  # a static base below 1.5 mm


@pytest.mark.parametrize("walls", [None, SideWalls(0.05, 0.3), SideWalls(0.02, 0.3)])
def test_the_profile_runs_from_rest_at_the_bed_to_the_surface_velocity_and_averages_to_the_depth_average(walls):
    for slope, h in ((22.0, 0.01), (26.0, 0.04), (31.0, 0.02)):
        ends = velocity(h, slope, walls=walls, z=np.array([0.0, h]))
        assert ends[0] == 0.0 and ends[1] == pytest.approx(float(velocity(h, slope, "surface", walls)), rel=1e-14)
        z = np.linspace(0.0, h, 20_001)
        v = velocity(h, slope, walls=walls, z=z)
        simpson = (v[0] + v[-1] + 4 * v[1:-1:2].sum() + 2 * v[2:-1:2].sum()) * (z[1] - z[0]) / 3 / h
        assert simpson == pytest.approx(float(velocity(h, slope, "depth_averaged", walls)), rel=1e-8)


@pytest.mark.parametrize("walls", [None, SideWalls(0.05, "mu_w")])
def test_the_profiles_derivatives_match_central_differences_and_are_finite_at_the_bed_and_the_surface(walls):
    h = np.array([0.03, 0.03, 0.03, 0.03, 0.03, 0.01, 0.01, 0.002])
    z = h * np.array([0.0, 1e-3, 0.4, 0.999, 1.0, 0.0, 0.6, 1.0])
    slope = np.array([22.0, 24.0, 26.0, 28.0, 30.0, 23.0, 25.0, 31.5])
    n = 4 if walls is not None else 3

    def f(theta):
        return steady_velocity(h, slope, theta[0], theta[1], theta[2], MATERIAL["rho"], MATERIAL["rho_s"],
                               MATERIAL["d"], "profile", walls, theta[3] if walls is not None else None, height=z)

    jacfwd, jacrev = jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f))
    for mu_w in (0.0, 0.3) if walls is not None else (None,):
        theta = np.array([TRUTH["mu1"], TRUTH["mu2"], TRUTH["I0"], mu_w][:n])
        forward, reverse = np.asarray(jacfwd(theta)), np.asarray(jacrev(theta))
        assert np.all(np.isfinite(forward)) and np.all(np.isfinite(reverse))
        np.testing.assert_allclose(reverse, forward, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(forward[z == 0.0], 0.0, atol=1e-12)  # the bed does not move, whatever they are
        step = 1e-6 * np.where(theta > 0, theta, 1.0)  # at mu_w = 0 across it: the closed form is smooth there
        fd = np.stack([(np.asarray(f(theta + e)) - np.asarray(f(theta - e))) / (2 * step[i])
                       for i, e in enumerate(np.diag(step))], axis=1)
        np.testing.assert_allclose(forward, fd, rtol=1e-6, atol=1e-10)
    # In the height: the shear rate, finite at both ends (0 at the free surface), against differences inside.
    theta = np.array([TRUTH["mu1"], TRUTH["mu2"], TRUTH["I0"], 0.3][:n])

    def g(heights):
        return steady_velocity(h, slope, *theta[:3], MATERIAL["rho"], MATERIAL["rho_s"], MATERIAL["d"], "profile",
                               walls, theta[3] if walls is not None else None, height=heights)

    dz, inner = np.diag(np.asarray(jax.jacfwd(g)(z))), (z > 0) & (z < h)
    assert np.all(np.isfinite(dz)) and np.all(dz[z == h] == 0.0) and np.all(dz >= 0.0)
    eps = 1e-7 * h
    np.testing.assert_allclose(dz[inner], ((np.asarray(g(z + eps)) - np.asarray(g(z - eps))) / (2 * eps))[inner],
                               rtol=1e-6)
    bed = z == 0.0  # at the bed: the shear rate there, by a one-sided difference (z < 0 is outside the layer)
    np.testing.assert_allclose(dz[bed], ((np.asarray(g(z + eps)) - np.asarray(g(z))) / eps)[bed], rtol=1e-4,
                               atol=1e-8)


def test_outside_the_layer_or_the_steady_range_it_is_nan_and_the_heights_go_with_a_profile_only():
    v = velocity(0.02, 25.0, z=np.array([-1e-4, 0.0, 0.01, 0.02, 0.0201]))
    assert np.isnan(v[0]) and np.isnan(v[-1]) and np.all(np.isfinite(v[1:-1]))
    slopes = np.array([math.degrees(math.atan(TRUTH["mu1"])) - 0.5, 25.0, math.degrees(math.atan(TRUTH["mu2"])) + 0.5])
    u = velocity(0.02, slopes, z=0.01)
    assert np.isnan(u[0]) and np.isfinite(u[1]) and np.isnan(u[2])
    with pytest.raises(ValueError, match='height: the heights z above the bed are given with quantity="profile" and '
                                         "only then, got quantity='profile' and height=None"):
        velocity(0.02, 25.0)
    with pytest.raises(ValueError, match="got quantity='surface' and height=heights"):
        velocity(0.02, 25.0, "surface", z=0.01)
    with pytest.raises(ValueError, match=r"quantity must be one of \('surface', 'depth_averaged', 'profile'\)"):
        velocity(0.02, 25.0, "mean")
