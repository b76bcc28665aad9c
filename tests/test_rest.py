"""Runs that stop when the flow stops (``Config.rest_speed``): the steps after the material is at
rest do nothing but carry the state to the frames and t_end, the observation at t_end is the
state at rest, gradients through such a run equal finite differences (float64), and a vmapped
batch in which one member rests and another does not equals the members run alone."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm

jax.config.update("jax_enable_x64", True)


def _scene(rest_speed, frames=()):
    """A block pushed into a floor and a frictional wall: its fastest particle falls below
    0.2 m/s at t = 0.135 s, so with rest_speed 0.2 and rest_duration 0.01 it is at rest at 0.145 s
    of 0.2 s."""
    dx = 0.05
    cfg = jm.Config(grid=jm.Grid((20, 16), dx), t_end=0.2, max_steps=2000,
                    walls=(jm.Wall((0, 0.1), (0, 1)), jm.Wall((0.1, 0), (1, 0), "non-separable", 0.3)),
                    frame_times=frames, rest_speed=rest_speed, rest_duration=0.01)
    x, vol = jm.seed_box((0.1, 0.1), (0.45, 0.4), dx, 2)
    v = 0.05 * np.random.default_rng(5).normal(size=x.shape) + np.array([-0.5, -0.3])
    return cfg, jm.init_state(cfg, x, vol, v=v, dtype="float64")


PARAMS = jm.Params.create(E=5e5)


@pytest.mark.parametrize("kw, match", [
    ({"rest_speed": 0.0}, "rest_speed"), ({"rest_speed": -1.0}, "rest_speed"),
    ({"rest_speed": float("nan")}, "rest_speed"), ({"rest_speed": float("inf")}, "rest_speed"),
    ({"rest_speed": 0.1, "rest_duration": -0.01}, "rest_duration"),
    ({"rest_duration": float("nan")}, "rest_duration"),
])
def test_bad_rest_options_name_the_argument(kw, match):
    with pytest.raises(ValueError, match=match):
        jm.Config(grid=jm.Grid((8, 8), 0.1), t_end=0.1, max_steps=10, **kw)


def test_at_rest_the_remaining_steps_do_nothing():
    cfg, s0 = _scene(0.2, frames=(0.05, 0.17, 0.19))
    final, frames = jax.jit(jm.make_rollout(cfg))(s0, PARAMS)
    moving, moving_frames = jax.jit(jm.make_rollout(dataclasses.replace(cfg, rest_speed=None)))(s0, PARAMS)
    quiet = float(final.quiet_since)
    assert 0.05 < quiet < 0.17 - cfg.rest_duration  # at rest between the first and second frames
    assert float(final.t) == cfg.t_end and int(final.status) == 0
    assert int(final.steps) < int(moving.steps) - 20
    assert np.isinf(float(moving.quiet_since))
    # The frames after the rest, and the state at t_end, are the state at rest, unchanged.
    np.testing.assert_array_equal(frames["x"][1], frames["x"][2])
    np.testing.assert_array_equal(frames["x"][2], final.x)
    assert np.all(np.linalg.norm(np.asarray(final.v), axis=1) < cfg.rest_speed)
    # Before the rest the two runs are the same run.
    np.testing.assert_array_equal(frames["x"][0], moving_frames["x"][0])
    # The run that goes on moves at most rest_speed x the time skipped (it decelerates further).
    skipped = cfg.t_end - quiet - cfg.rest_duration
    assert np.abs(np.asarray(final.x) - np.asarray(moving.x)).max() < cfg.rest_speed * skipped


@pytest.mark.slow  # 16 s; the rest check's other properties are tested by default
def test_gradient_through_a_run_that_rests_matches_finite_differences():
    cfg, s0 = _scene(0.2)
    rollout = jm.make_rollout(cfg, observer=None)

    def loss(params):
        final, _ = rollout(s0, params)
        return jnp.mean(final.x[:, 0]) + 2.0 * jnp.mean(final.x[:, 1]), final.steps

    grads, steps = jax.jit(jax.grad(loss, has_aux=True))(PARAMS)
    f = jax.jit(loss)
    for key in ("E", "rho"):
        value = getattr(PARAMS, key)
        h = 1e-6 * value
        up, steps_up = f(PARAMS.replace(**{key: value + h}))
        down, steps_down = f(PARAMS.replace(**{key: value - h}))
        # The difference is taken across runs that rest at the same step (the stop is a discrete
        # decision; the derivative is that of the run actually taken).
        assert int(steps_up) == int(steps_down) == int(steps)
        g = getattr(grads, key)
        assert np.isfinite(g) and g != 0
        np.testing.assert_allclose(g, (up - down) / (2 * h), rtol=1e-5, err_msg=key)


def test_vmapped_batch_in_which_one_member_rests_equals_the_members_alone():
    cfg, s0 = _scene(0.2)
    rollout = jm.make_rollout(cfg, observer=None)
    batch = jax.tree.map(lambda *p: jnp.stack(p), PARAMS, PARAMS.replace(rho=4.0 * PARAMS.rho))

    def run(params):
        final, _ = rollout(s0, params)
        return final.x, final.steps, final.quiet_since

    together = jax.jit(jax.vmap(run))(batch)
    for i in range(2):
        alone = jax.jit(run)(jax.tree.map(lambda p, i=i: p[i], batch))
        np.testing.assert_allclose(together[0][i], alone[0], rtol=0, atol=1e-12)
        assert int(together[1][i]) == int(alone[1])
    # The heavier block is still moving: the batch holds one member at rest and one not.
    assert np.isfinite(float(together[2][0])) and int(together[1][1]) != int(together[1][0])
