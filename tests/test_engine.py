"""The step and rollout: free fall, exact frame times, the step budget, status bits, no
recompilation, vmap, and input validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm


def _block(dim=2, t_end=0.1, max_steps=500, frames=(), walls=None, v=None, gravity=None, transfer="aflip",
           E=1e6, lower=None, upper=None, cells=None):
    dx = 0.05
    cells = cells or (24,) * dim
    walls = (jm.Wall((0.0,) * (dim - 1) + (0.1,), (0.0,) * (dim - 1) + (1.0,)),) if walls is None else walls
    cfg = jm.Config(grid=jm.Grid(cells, dx), t_end=t_end, max_steps=max_steps, walls=walls,
                    frame_times=frames, gravity=gravity, transfer=transfer)
    lower = lower or (0.4,) * (dim - 1) + (0.3,)
    upper = upper or (0.7,) * (dim - 1) + (0.55,)
    x, vol = jm.seed_box(lower, upper, dx, 2)
    return cfg, jm.init_state(cfg, x, vol, v=v), jm.Params.create(E=E)


@pytest.mark.parametrize("dim", [2, 3])
def test_free_fall_is_exact_symplectic_euler(dim):
    """No walls, no stress: each step is v += dt g, x += dt v (symplectic Euler) to round-off;
    the continuous ballistic solution is met to within the scheme's O(dt) term, ½|g| t dt."""
    g = np.array([0.7, -9.81, 0.3][:dim])
    v0 = np.array([0.2, 0.5, -0.1][:dim])
    # A soft material (E = 100 Pa) so that the CFL bound, which shrinks as |v| grows, sets dt.
    cfg, s, params = _block(dim, t_end=0.3, walls=(), gravity=tuple(g), v=v0, E=100.0,
                            lower=(0.5,) * (dim - 1) + (0.9,), upper=(0.7,) * (dim - 1) + (1.1,), cells=(30,) * dim)
    step = jax.jit(jm.make_step(cfg))
    x0 = np.asarray(s.x)
    x_ref, v_ref, t = x0.copy(), np.broadcast_to(v0, x0.shape).copy(), 0.0
    dts = []
    while float(s.t) < cfg.t_end:
        s = step(s, params)
        dt = float(s.dt)
        dts.append(dt)
        v_ref = v_ref + dt * g
        x_ref = x_ref + dt * v_ref
        t += dt
    assert float(s.t) == cfg.t_end and s.status == 0
    assert len(set(dts[:-1])) > 1  # the adaptive step really varied (the CFL term grows with |v|)
    np.testing.assert_allclose(s.v, v_ref, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(s.x, x_ref, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(s.C, 0.0, atol=1e-12)
    np.testing.assert_allclose(s.F, np.broadcast_to(np.eye(dim), s.F.shape), atol=1e-12)
    ballistic = x0 + v0 * t + 0.5 * g * t**2
    bound = 0.5 * np.linalg.norm(g) * t * max(dts) * 1.0001
    assert np.max(np.linalg.norm(np.asarray(s.x) - ballistic, axis=1)) <= bound


def test_frames_land_exactly_and_steps_after_end_do_nothing():
    frames = (0.0, 0.0123, 0.05, 0.0777)
    cfg, s0, params = _block(t_end=0.0777, max_steps=400, frames=frames)
    result = jm.simulate(cfg, s0, params)
    assert result.status == 0
    assert float(result.state.t) == 0.0777
    np.testing.assert_array_equal(result.frames["x"][0], s0.x)
    steps = int(result.state.steps)
    assert steps < 400
    # Frame k is the state after the step that landed on frame_times[k]: a run that ends there
    # (with the same earlier stop) takes the same steps.
    cfg2, _, _ = _block(t_end=0.05, max_steps=400, frames=(0.0123,))
    mid = jm.simulate(cfg2, s0, params, observer=None)
    np.testing.assert_allclose(result.frames["x"][2], mid.state.x, rtol=0, atol=0)


def test_step_budget_bit_and_raise():
    cfg, s0, params = _block(t_end=0.5, max_steps=10)
    with pytest.raises(jm.SimulationError, match="step budget"):
        jm.simulate(cfg, s0, params)
    result = jm.simulate(cfg, s0, params, throw=False)
    assert result.status & jm.BUDGET
    assert int(result.state.steps) == 10 and float(result.state.t) < 0.5
    # Ten steps in blocks of three: the last block's two steps past the budget do nothing, in the
    # compiled rollout and block by block alike (which ran twelve before the budget guard).
    assert cfg.blocks == (4, 3)
    timed = jm.simulate(cfg, s0, params, throw=False, timed=True)
    assert timed.status == result.status and int(timed.state.steps) == 10
    for a, b in zip(jax.tree.leaves(timed.state), jax.tree.leaves(result.state)):
        np.testing.assert_array_equal(a, b)


def test_left_grid_bit():
    cfg, s0, params = _block(t_end=0.3, walls=(), max_steps=2000)  # no floor: it falls out
    result = jm.simulate(cfg, s0, params, throw=False)
    assert result.status & jm.LEFT_GRID
    with pytest.raises(jm.SimulationError, match="left the grid"):
        jm.simulate(cfg, s0, params)


def test_inversion_and_nonfinite_bits():
    # A violent converging velocity with a huge cfl inverts particles within a step.
    cfg, s0, params = _block(t_end=0.1, max_steps=50)
    cfg = jm.Config(**{**cfg.__dict__, "cfl": 50.0, "cfl_elastic": 50.0})
    v = -200.0 * (s0.x - jnp.mean(s0.x, axis=0))
    result = jm.simulate(cfg, s0.replace(v=v), params, throw=False)
    assert result.status & jm.J_NONPOSITIVE
    # Non-finite initial stress propagates and is flagged.
    tau = s0.tau.at[0, 0, 0].set(jnp.nan)
    result = jm.simulate(cfg, s0.replace(tau=tau), params, throw=False)
    assert result.status & jm.NONFINITE


def test_no_recompile_for_new_parameters_and_vmap_equals_loop():
    cfg, s0, params = _block(t_end=0.03, frames=(0.01, 0.03))
    traces = []

    def observer(state, params):
        traces.append(1)  # runs at trace time only
        return {"ymean": jnp.mean(state.x[:, 1])}

    runs = [jm.simulate(cfg, s0, jm.Params.create(E=E), observer=observer) for E in (5e5, 1e6, 2e6, 4e6)]
    n_traces = len(traces)
    jm.simulate(cfg, s0, jm.Params.create(E=3e6, nu=0.2), observer=observer)
    assert len(traces) == n_traces, "a second call with new parameter values recompiled"
    assert jm.compiled_rollout(cfg, observer)._cache_size() == 1

    batch = jax.tree.map(lambda *v: jnp.stack(v), *[jm.Params.create(E=E) for E in (5e5, 1e6, 2e6, 4e6)])
    final, frames = jax.jit(jax.vmap(jm.make_rollout(cfg, observer), in_axes=(None, 0)))(s0, batch)
    for i, r in enumerate(runs):
        np.testing.assert_allclose(final.x[i], r.state.x, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(frames["ymean"][i], r.frames["ymean"], rtol=1e-12)
        assert int(final.steps[i]) == int(r.state.steps)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: jm.Grid((10, 10), -0.01), "dx must be > 0"),
        (lambda: jm.Grid((10, 10), 0.0), "dx must be > 0"),
        (lambda: jm.Params.create(E=0.0), "E must be > 0"),
        (lambda: jm.Params.create(E=-1e6), "E must be > 0"),
        (lambda: jm.Params.create(nu=0.5), r"nu must be in \(-1, 0.5\)"),
        (lambda: jm.Params.create(nu=-1.0), r"nu must be in \(-1, 0.5\)"),
        (lambda: jm.Params.create(rho=float("nan")), "rho must be finite"),
        (lambda: jm.Params.create(mu1=float("inf")), "mu1 must be finite"),
        (lambda: jm.Params.create(foo=1.0), "unknown parameter"),
        (lambda: jm.init_state(_block()[0], np.zeros((0, 2)), 1.0), "x is empty"),
        (lambda: jm.init_state(_block()[0], np.array([[5.0, 0.3]]), 1.0), "outside the grid"),
        (lambda: jm.init_state(_block()[0], np.array([[0.3, 0.3]]), -1.0), "vol0 must be > 0"),
        (lambda: jm.Config(grid=jm.Grid((10, 10), 0.1), t_end=0.0, max_steps=10), "t_end must be > 0"),
        (lambda: jm.Config(grid=jm.Grid((10, 10), 0.1), t_end=1.0, max_steps=0), "max_steps"),
        (lambda: jm.Config(grid=jm.Grid((10, 10), 0.1), t_end=1.0, max_steps=9, transfer="flip"), "transfer"),
        (lambda: jm.Config(grid=jm.Grid((10, 10), 0.1), t_end=1.0, max_steps=9, frame_times=(2.0,)), "frame_times"),
        (lambda: jm.Wall((0, 0), (0, 0)), "Wall.normal must be a non-zero vector"),
        (lambda: jm.Wall((0, 0), (0, 1), kind="sticky"), "Wall.kind"),
        (lambda: jm.Wall((0, 0), (0, 1), friction=-0.1), "Wall.friction"),
    ],
)
def test_input_errors_name_the_argument(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_simulate_validates_before_tracing():
    cfg, s0, params = _block()
    bad = params.replace(E=jnp.asarray(-1.0))
    with pytest.raises(ValueError, match="E must be > 0"):
        jm.simulate(cfg, s0, bad)
    batch = jax.tree.map(lambda v: jnp.stack([v, v]), params).replace(nu=jnp.asarray([0.3, 0.7]))
    with pytest.raises(ValueError, match=r"nu must be in \(-1, 0.5\), got 0.7"):
        jm.simulate(cfg, s0, batch)
    with pytest.raises(ValueError, match="outside the grid"):
        jm.simulate(cfg, s0.replace(x=s0.x.at[3, 0].set(-1.0)), params)


def test_wall_rules_of_the_three_types():
    """docs/model.md §5 on single nodes of a floor (normal +y, μ_w = 0.5, dt = 0), with relative
    velocity v = (v_t, v_n): no-slip gives 0 everywhere; non-separable removes v_n on every
    contact node and charges |v_t| <- max(0, |v_t| − μ_w |v_n|) whatever the sign of v_n;
    separable does the same only where v_n < 0 (pressed) and leaves a separating node alone.
    Nodes above the floor are never touched. The reference code's names map to these."""
    from jaxmpm.boundary import apply_walls

    node_x = jnp.asarray([[0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 1.0]])  # (dim, nodes)
    v = jnp.asarray([[1.0, 1.0, 0.2, -1.0, 1.0], [-1.0, 1.0, -1.0, 0.4, -1.0]])
    expect = {
        "no-slip": [[0, 0, 0, 0, 1.0], [0, 0, 0, 0, -1.0]],
        "non-separable": [[0.5, 0.5, 0.0, -0.8, 1.0], [0, 0, 0, 0, -1.0]],
        "separable": [[0.5, 1.0, 0.0, -1.0, 1.0], [0, 1.0, 0, 0.4, -1.0]],
    }
    for kind, want in expect.items():
        wall = jm.Wall((0.0, 0.0), (0.0, 1.0), kind=kind, friction=0.5)
        got = apply_walls((wall,), v, node_x, 0.0, 0.0)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-15, err_msg=kind)
    assert jm.Wall((0, 0), (0, 1), kind="slip-stick").kind == "non-separable"
    assert jm.Wall((0, 0), (0, 1), kind="slip-free").kind == "separable"


def test_elastic_time_step_is_the_reference_rule_and_stable_near_incompressible():
    """dt_e = cfl_e dx / c: for −0.45 <= ν <= 0.32, c = sqrt(E/ρ) exactly (the reference code's
    rule), and dc/dν = 0 at the default ν = 0.3 (no kink there: the rollout's d/dν is checked
    against finite differences in test_gradients.py); for every admitted ν the P-wave Courant
    number cfl_e c_p / c stays at or below 0.6, where sqrt(E/ρ) alone gives 6.5 at ν = 0.499
    (a silent blow-up: S2 ran 15 % too far at ν = 0.499, docs/validation.md)."""
    from jaxmpm.materials.base import lame

    mat = jm.Hencky()
    for nu in (-0.5, -0.45, 0.0, 0.2, 0.3, 0.32, 0.35, 0.45, 0.49, 0.499):
        params = jm.Params.create(E=1e6, nu=nu, rho=1550.0)
        c = float(mat.wave_speed(params))
        G, lam = (float(v) for v in lame(params))
        c_p = np.sqrt((lam + 2 * G) / 1550.0)
        if -0.45 <= nu <= 0.32:
            assert c == pytest.approx(np.sqrt(1e6 / 1550.0), rel=1e-12)
        assert 0.5 * c_p / c <= 0.6 * (1 + 1e-12)
    dc = jax.grad(lambda nu: mat.wave_speed(jm.Params.create(E=1e6, rho=1550.0).replace(nu=nu)))(jnp.asarray(0.3))
    assert float(dc) == 0.0


@pytest.mark.parametrize("transfer", ["apic", "aflip"])
def test_wall_impulses_close_the_momentum_balance(transfer):
    """The impulse each wall records is the momentum it took from the material: in float64,
    M v̄(t) = M g t − Σ_walls impulse to round-off at every frame (APIC and AFLIP transfers
    conserve momentum). The suite runs in x64 (conftest.py)."""
    g = (0.0, -9.81)
    walls = (jm.Wall((0.0, 0.1), (0.0, 1.0), "separable", 0.3), jm.Wall((0.38, 0.0), (1.0, 0.0), "no-slip"))
    cfg, s0, params = _block(t_end=0.3, max_steps=2000, frames=(0.1, 0.2, 0.3), walls=walls, gravity=g,
                             transfer=transfer, E=2e5, v=(-0.5, 0.0))
    assert s0.x.dtype == jnp.float64
    out = jm.simulate(cfg, s0, params, observer=lambda s, p: {"v": s.v, "impulse": s.impulse, "t": s.t})
    mass = np.asarray(params.rho * s0.vol0)
    momentum = np.einsum("n,tnd->td", mass, np.asarray(out.frames["v"]))
    impulse = np.asarray(out.frames["impulse"])
    t = np.asarray(out.frames["t"])
    gravity = mass.sum() * np.outer(t, g)
    balance = momentum + impulse.sum(axis=1) - gravity - mass.sum() * np.array([-0.5, 0.0])
    assert np.max(np.abs(balance)) < 1e-10 * mass.sum() * 9.81 * t[-1], balance
    assert impulse[-1, 1, 0] < 0  # the block was thrown against the left wall: pushed in −x
    assert impulse[-1, 0, 1] < 0  # it landed on the floor
    assert np.all(np.abs(impulse[-1]) > 0)
