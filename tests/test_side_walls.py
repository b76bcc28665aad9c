"""The side walls of a 2D channel (``jaxmpm.SideWalls``): their friction on the grid nodes, the
steady flow between them against its analytic solution, and their gradient (float64)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxmpm as jm
from jaxmpm import SideWalls, scenes
from jaxmpm.boundary import side_wall_friction
from jaxmpm.scenes.incline import S1_DEPTH, side_wall_velocity


@pytest.mark.parametrize("kwargs, message", [
    (dict(width=-0.02, friction=0.25), "SideWalls.width must be finite and > 0"),
    (dict(width=0.0, friction=0.25), "SideWalls.width must be finite and > 0"),
    (dict(width=0.02, friction=-0.1), "SideWalls.friction must be finite and >= 0"),
    (dict(width=0.02, friction=0.2, lateral_pressure_ratio=math.nan), "lateral_pressure_ratio must be finite"),
    (dict(width="wide", friction=0.2), "SideWalls.width must be a number"),
])
def test_bad_side_walls_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SideWalls(**kwargs)


def test_side_walls_are_refused_in_3d():
    grid = jm.Grid((4, 4, 4), 0.1)
    with pytest.raises(ValueError, match="side_walls is the 2D model"):
        jm.Config(grid=grid, t_end=1.0, max_steps=10, side_walls=SideWalls(0.02, 0.2))


def test_node_friction_stops_a_node_but_never_reverses_it():
    side = SideWalls(width=0.1, friction=0.4, lateral_pressure_ratio=0.5)
    v = jnp.array([[3.0, 0.1, 0.0, -2.0], [4.0, 0.0, 0.0, 0.0]])
    mass = jnp.array([2.0, 2.0, 0.0, 1.0])
    pressure = jnp.array([50.0, 50.0, 50.0, 10.0])
    dt = 1e-2
    out = np.asarray(side_wall_friction(side, v, pressure, mass, dt))
    c = 2 * 0.4 * 0.5 * dt / 0.1 * np.array([25.0, 25.0, 0.0, 10.0])  # 2 μ K dt P / (W m)
    np.testing.assert_allclose(out[:, 0], np.array([3.0, 4.0]) * (1 - c[0] / 5.0), rtol=1e-12)  # the direction kept
    np.testing.assert_array_equal(out[:, 1], 0.0)  # slower than c: stopped, not reversed
    np.testing.assert_array_equal(out[:, 2], 0.0)  # an empty node
    np.testing.assert_allclose(out[:, 3], [-2.0 + c[3], 0.0], rtol=1e-12)
    # At rest the derivative is finite (zero), not NaN; elsewhere it is the differences'.
    grad = jax.grad(lambda u: jnp.sum(side_wall_friction(side, u, pressure, mass, dt)))(jnp.zeros_like(v))
    assert np.all(np.isfinite(np.asarray(grad)))
    sliding = (jnp.array([[3.0, -2.0], [4.0, 0.5]]), jnp.array([50.0, 10.0]), jnp.array([2.0, 1.0]))
    check_grads(lambda u, p, m: side_wall_friction(side, u, p, m, dt), sliding, order=1, modes=("fwd", "rev"))


def _strip(slope, side_walls, t_end=0.5, division=16, frames=4, **values):
    return scenes.incline(slope, dx=S1_DEPTH / division, t_end=t_end, frames=frames, critical_start=True,
                          side_walls=side_walls, **values)


@pytest.mark.slow  # 20 s: two critical-state compiles; side_walls=None is the engine's own code path
def test_side_walls_vanish_without_friction_and_as_one_over_the_width():
    """Plane strain is the limit of the side-wall term: with μ_w = 0 it multiplies every node's
    velocity by exactly 1 (the run is the one without side walls, ``side_walls=None``), and as
    W -> ∞ its effect falls as 1/W (the friction per unit volume is 2 μ_w K p / W)."""
    config, state, params = _strip(26.0, None, t_end=0.02, frames=0)
    plain = jm.simulate(config, state, params).state
    assert int(plain.steps) > 20

    def walled(walls):  # the same start: the walls' scene would start from their own steady flow
        return jm.simulate(dataclasses.replace(config, side_walls=walls), state, params).state

    np.testing.assert_array_equal(walled(SideWalls(0.05, 0.0)).x, plain.x)
    shift = {w: float(np.abs(np.asarray(walled(SideWalls(w, 0.3)).v) - np.asarray(plain.v)).max()) for w in (1e2, 1e4)}
    assert 0 < shift[1e4] < shift[1e2] < 1e-3 * float(np.abs(np.asarray(plain.v)).max())
    np.testing.assert_allclose(shift[1e4] / shift[1e2], 1e-2, rtol=0.05)


@pytest.mark.slow  # 19 s: a physics check at scale (also `python -m jaxmpm validate side-walls`); the node
# rule runs by default (test_node_friction_stops_a_node_but_never_reverses_it)
def test_the_steady_flow_between_side_walls_is_the_analytic_one():
    """S1 at 28° between walls 5 cm apart (μ_w = 0.3): the flow stops 25 mm below the surface
    of the 38 mm layer and the surface runs at 0.85 m/s, against 2.6 m/s without walls. Started
    on that profile, the strip holds it: after 0.5 s the surface velocity is within 3 % of it and
    the profile within 3 % of it (RMS over the particles, of the surface velocity)."""
    side = SideWalls(width=0.05, friction=0.3)
    scene = _strip(28.0, side)
    _, stop = side_wall_velocity(0.0, S1_DEPTH, 28.0, scene.params, side)
    assert stop == pytest.approx(0.05 * (math.tan(math.radians(28.0)) - float(scene.params.mu1)) / 0.3)
    result = jm.simulate(*scene, observer=lambda s, p: {"vx": s.v[:, 0], "y": s.x[:, 1]})
    assert result.status == 0
    vx, z = np.asarray(result.frames["vx"][-1]), np.asarray(result.frames["y"][-1]) - scene.info.wall_gap
    analytic, _ = side_wall_velocity(z, S1_DEPTH, 28.0, scene.params, side)
    top = np.argsort(z)[-scene.config.grid.cells[0] * scene.info.ppc:]
    v_max = side_wall_velocity(S1_DEPTH, S1_DEPTH, 28.0, scene.params, side)[0]
    assert vx[top].mean() == pytest.approx(analytic[top].mean(), rel=0.03)
    assert np.sqrt(np.mean((vx - analytic) ** 2)) < 0.03 * v_max
    assert np.all(np.abs(vx[z < S1_DEPTH - stop - scene.info.dx]) < 0.03 * v_max)  # below ζ*: at rest
    assert scenes.bagnold_velocity(S1_DEPTH, S1_DEPTH, 28.0, scene.params) > 3 * v_max


@pytest.mark.slow  # 27 s: a reverse-mode compile of the critical-state rollout; the node rule's own
def test_the_side_walls_gradient_matches_finite_differences():  # derivatives are checked by default
    """d(mean velocity along the slope after 40 steps)/d(μ1, ρ, μ_w) with side walls whose friction
    is the parameter, float64, against central differences (relative step 1e-6), to 1e-5."""
    scene = _strip(28.0, SideWalls(0.05, "mu_w"), t_end=1.0, division=8, frames=0, mu_w=0.3)
    scene = dataclasses.replace(scene, config=dataclasses.replace(scene.config, max_steps=40))
    rollout = jm.make_rollout(scene.config, observer=None)

    def mean_speed(params):
        final, _ = rollout(scene.state, params)
        return jnp.mean(final.v[:, 0])

    grads = jax.jit(jax.grad(mean_speed))(scene.params)
    f = jax.jit(mean_speed)
    for key in ("mu1", "rho", "mu_w"):
        value = getattr(scene.params, key)
        h = 1e-6 * value
        fd = (f(scene.params.replace(**{key: value + h})) - f(scene.params.replace(**{key: value - h}))) / (2 * h)
        assert np.isfinite(getattr(grads, key))
        np.testing.assert_allclose(getattr(grads, key), fd, rtol=1e-5, err_msg=key)


# ---- the walls' friction as the parameter mu_w --------------------------------------------------------------
def test_walls_declared_mu_w_take_the_parameter_and_equal_the_number():
    """``SideWalls(W, "mu_w")`` reads ``Params.mu_w``: a run equals the one with the number, and
    the node rule takes μ_w from the parameters (refused without them)."""
    side, fixed = SideWalls(0.05, "mu_w"), SideWalls(0.05, 0.3)
    v = jnp.array([[3.0, -2.0], [4.0, 0.5]])
    pressure, mass = jnp.array([50.0, 10.0]), jnp.array([2.0, 1.0])
    params = jm.Params.create(mu_w=0.3)
    np.testing.assert_array_equal(side_wall_friction(side, v, pressure, mass, 1e-2, params),
                                  side_wall_friction(fixed, v, pressure, mass, 1e-2))
    with pytest.raises(ValueError, match="needs the parameters"):
        side_wall_friction(side, v, pressure, mass, 1e-2)
    with pytest.raises(ValueError, match="SideWalls.friction must be a number >= 0 or the parameter name 'mu_w'"):
        SideWalls(0.05, "mu")
    config, state = _sliding_block(fixed)
    declared = dataclasses.replace(config, side_walls=side)
    assert not config.reads_mu_w and declared.reads_mu_w
    plain, walled = jax.jit(jm.make_step(config)), jax.jit(jm.make_step(declared))
    a = b = state
    for _ in range(5):
        a, b = plain(a, params.replace(mu_w=0.0)), walled(b, params)
    np.testing.assert_allclose(b.v, a.v, rtol=1e-12, atol=1e-15)
    assert float(jnp.abs(a.v - state.v).max()) > 0


def _sliding_block(side_walls, max_steps=10):
    """An elastic block, compressed (F = 0.98 I: a pressure for the walls to act on), sliding at
    1 m/s along a no-slip floor's row, between ``side_walls``."""
    config = jm.Config(grid=jm.Grid((16, 12), 0.05), t_end=1.0, max_steps=max_steps,
                       walls=(jm.Wall((0.0, 0.1), (0.0, 1.0)),), side_walls=side_walls)
    x, vol = jm.seed_box((0.2, 0.1), (0.5, 0.3), 0.05, 2)
    state = jm.init_state(config, x, vol, v=np.tile([1.0, 0.0], (len(x), 1)))
    return config, state.replace(F=0.98 * state.F)


def test_the_walls_mu_w_derivative_matches_finite_differences():
    """d(mean velocity after 3 steps)/d μ_w of walls declared "mu_w", through the whole step, in
    forward mode (the calibration's Jacobians), float64, against central differences (relative
    step 1e-6), to 1e-6; and not zero (the walls act), on the elastic sliding block (reverse mode
    through the critical state: the slow test above)."""
    config, state = _sliding_block(SideWalls(0.05, "mu_w"), max_steps=3)
    rollout, params = jm.make_rollout(config, observer=None, checkpoint=False), jm.Params.create()

    def mean_speed(mu_w):
        final, _ = rollout(state, params.replace(mu_w=mu_w))
        return jnp.mean(final.v[:, 0])

    _, grad = jax.jit(lambda m: jax.jvp(mean_speed, (m,), (jnp.ones_like(m),)))(jnp.asarray(0.3))
    f, h = jax.jit(mean_speed), 1e-6 * 0.3
    fd = (f(0.3 + h) - f(0.3 - h)) / (2 * h)
    assert np.isfinite(grad) and grad < 0  # more friction, slower
    np.testing.assert_allclose(grad, fd, rtol=1e-6)
