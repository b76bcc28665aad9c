"""Terrain of any shape as a frictional boundary (docs/scenes.md S6): the polyline's signed
distance and normal, a block sliding on a 30° polyline at the Coulomb speed, a block stopping on a
hockey stick where a sliding point mass does (and near the energy line), independence from where
the vertices fall, and the gradient with respect to the terrain's friction μ_w."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.rollout import make_rollout
from jaxmpm.step import step_budget

G = 9.81
THETA = math.radians(30.0)
TANGENT = np.array([math.cos(THETA), -math.sin(THETA)])  # down the slope
NORMAL = np.array([math.sin(THETA), math.cos(THETA)])
Z0 = 0.8


def _slope(vertices_x, **kw):
    x = np.asarray(vertices_x, float)
    return jm.Terrain(tuple(x), tuple(Z0 - math.tan(THETA) * x), **kw)


def test_terrain_rejects_bad_input():
    with pytest.raises(ValueError, match="Terrain.x must increase strictly"):
        jm.Terrain((0.0, 1.0, 1.0), (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="same length"):
        jm.Terrain((0.0, 1.0), (0.0,))
    with pytest.raises(ValueError, match="at least 2 vertices"):
        jm.Terrain((0.0,), (0.0,))
    with pytest.raises(ValueError, match="Terrain.friction"):
        jm.Terrain((0.0, 1.0), (0.0, 0.0), friction="mu")
    with pytest.raises(ValueError, match="Terrain.friction must be finite and >= 0"):
        jm.Terrain((0.0, 1.0), (0.0, 0.0), friction=-0.1)
    with pytest.raises(ValueError, match="Terrain.kind"):
        jm.Terrain((0.0, 1.0), (0.0, 0.0), kind="sticky")
    with pytest.raises(ValueError, match="Terrain.x must be finite"):
        jm.Terrain((0.0, float("nan")), (0.0, 0.0))
    with pytest.raises(ValueError, match=r"walls\[0\] is 2D but the grid is 3D"):
        jm.Config(grid=jm.Grid((4, 4, 4), 0.1), t_end=0.1, max_steps=10, walls=(jm.Terrain((0.0, 1.0), (0.0, 0.0)),))
    with pytest.raises(ValueError, match="needs the parameters"):
        jm.boundary.apply_walls((_slope([0.0, 1.0], friction="mu_w"),), jnp.zeros((2, 3)), jnp.zeros((2, 3)), 0.0, 0.0)


def test_signed_distance_is_exact_on_a_straight_slope_and_continuous_at_a_bend():
    """On a straight polyline φ is the exact distance to its line and n its normal, wherever
    the vertices are; across a bend's vertex φ and n are continuous, and the sign of φ is the
    side of the polyline at every point."""
    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.uniform([-0.2, 0.0], [1.4, 1.0], size=(200, 2)).T, jnp.float32)
    exact = (np.asarray(p[1]) - (Z0 - math.tan(THETA) * np.asarray(p[0]))) * math.cos(THETA)
    for vertices in ([0.0, 1.2], [0.0, 0.137, 0.5, 0.71, 1.2]):
        phi, n = _slope(vertices).signed_distance(p)
        np.testing.assert_allclose(phi, exact, atol=2e-6)
        np.testing.assert_allclose(n, np.broadcast_to(NORMAL[:, None], n.shape), atol=1e-6)

    bend = jm.Terrain((0.0, 1.0, 2.0), (1.0, 0.0, 0.0))  # 45° into flat, vertex at x = 1
    x = jnp.asarray([1.0 - 1e-4, 1.0, 1.0 + 1e-4])
    for height in (0.0, 0.05, -0.05):
        phi, n = bend.signed_distance(jnp.stack([x, jnp.full_like(x, height)]))
        assert np.ptp(np.asarray(phi)) < 1e-3 and np.max(np.ptp(np.asarray(n), axis=1)) < 1e-3, (phi, n)
        assert np.all(np.sign(phi) == np.sign(height)) or height == 0.0
    np.testing.assert_allclose(bend.height(np.asarray([0.5, 1.0, 3.0])), [0.5, 0.0, 0.0])


def _block_on_slope(vertices=(0.0, 0.137, 0.5, 0.71, 1.2), dx=0.02, transfer="pic", t_end=0.1, n_frames=10,
                    mu_w=0.1, dtype=None):
    """An elastic block (0.2 m along the slope × 0.1 m, E = 1e6, ν = 0.3, ρ = 1550) at rest on a
    30° polyline whose friction is the parameter μ_w, its lower face half a cell above it,
    under plain vertical gravity: the grid is not aligned with the slope."""
    xs, vol = jm.seed_box((0.0, 0.0), (0.2, 0.1), dx, 2)
    xs = np.asarray(xs)
    x = np.array([0.0, Z0]) + (0.2 + xs[:, :1]) * TANGENT + (0.5 * dx + xs[:, 1:]) * NORMAL
    frames = tuple(np.linspace(t_end / n_frames, t_end, n_frames)) if n_frames else ()
    cfg = jm.Config(grid=jm.Grid((math.ceil(1.2 / dx), math.ceil(1.0 / dx)), dx), t_end=t_end, max_steps=3000,
                    walls=(_slope(vertices, friction="mu_w"),), transfer=transfer, frame_times=frames)
    params = jm.Params.create(E=1e6, nu=0.3, rho=1550.0, mu_w=mu_w, dtype=dtype)
    return cfg, jm.init_state(cfg, x, vol, dtype=dtype), params


def _mean(s, params):
    w = s.vol0[:, None] / jnp.sum(s.vol0)
    return {"v": jnp.sum(s.v * w, 0), "x": jnp.sum(s.x * w, 0)}


@pytest.mark.parametrize("transfer", ["pic", "aflip"])
def test_block_slides_on_a_polyline_at_the_coulomb_speed(transfer):
    """A block on a 30° polyline with μ_w = 0.1 reaches v = g t (sin θ − μ_w cos θ) = 0.4055 m/s
    at t = 0.1 s, within 1 % (measured −0.11 % with PIC, −0.44 % with AFLIP at dx = 0.02), and
    stays on the ground (normal drift of its centre below 0.2 dx; measured 0.05 dx)."""
    cfg, state, params = _block_on_slope(transfer=transfer)
    result = jm.simulate(cfg, state, params, observer=_mean)
    assert result.state.status == 0, result.status_text
    v = np.asarray(result.frames["v"])
    x = np.asarray(result.frames["x"])
    expected = G * 0.1 * (math.sin(THETA) - 0.1 * math.cos(THETA))
    assert abs(v[-1] @ TANGENT / expected - 1.0) < 0.01, (v[-1] @ TANGENT, expected)
    assert np.max(np.abs((x - x[0]) @ NORMAL)) < 0.2 * 0.02


@pytest.mark.slow  # 15 s; the signed distance's continuity at a bend stays in the default suite
def test_terrain_result_does_not_depend_on_where_the_vertices_fall():
    """The same straight slope given by 2 vertices or by 5 at arbitrary places (relative to the
    grid) gives the same run to float32 round-off."""
    runs = []
    for vertices in ((-0.3, 1.5), (0.0, 0.137, 0.5, 0.71, 1.2), (0.0, 0.3 + 0.02 * 0.5, 0.61, 1.2)):
        cfg, state, params = _block_on_slope(vertices=vertices, t_end=0.05, n_frames=5)
        runs.append(np.asarray(jm.simulate(cfg, state, params, observer=_mean).frames["v"]))
    for other in runs[1:]:
        np.testing.assert_allclose(other, runs[0], rtol=1e-4, atol=1e-6)


@pytest.mark.slow  # 18 s; finite wall-friction tangents are checked by default (tests/test_gradients.py)
def test_gradient_with_respect_to_terrain_friction_matches_finite_differences():
    """d(mean downslope speed at t = 0.05 s)/dμ_w through the whole sliding run, reverse mode
    against central differences in float64 (the test suite's precision; measured agreement 1e-10
    relative). It is near the rigid-block value −g t cos θ = −0.425 (measured −0.454: the normal
    force overshoots while the contact builds up in the first steps)."""
    cfg, state, params = _block_on_slope(dx=0.025, t_end=0.05, n_frames=0, dtype=jnp.float64)
    rollout = make_rollout(cfg, observer=None)
    tangent = jnp.asarray(TANGENT)

    def speed(mu):
        final = rollout(state, params.replace(mu_w=mu))[0]
        return jnp.sum((final.v @ tangent) * final.vol0) / jnp.sum(final.vol0)

    grad = float(jax.jit(jax.grad(speed))(jnp.float64(0.1)))
    f = jax.jit(speed)
    h = 1e-4
    fd = float((f(0.1 + h) - f(0.1 - h)) / (2 * h))
    assert math.isfinite(grad)
    assert abs(grad - fd) < 1e-6 * abs(fd), (grad, fd)
    assert abs(grad / (-G * 0.05 * math.cos(THETA)) - 1.0) < 0.15, grad


# A hockey stick: a 30° slope down to x1, a circular arc of radius R tangent to it and to the
# flat floor that starts at x2 = x1 + R sin θ.
HS = {"x1": 0.3, "R": 1.0, "z0": 1.0, "flat": 0.5}
HS["x2"] = HS["x1"] + HS["R"] * math.sin(THETA)
HS["z_flat"] = HS["z0"] - math.tan(THETA) * HS["x1"] - HS["R"] * (1 - math.cos(THETA))


def _hockey_stick(x):
    """(z, dz/dx, d²z/dx²) of the hockey stick at x."""
    if x <= HS["x1"]:
        return HS["z0"] - math.tan(THETA) * x, -math.tan(THETA), 0.0
    if x <= HS["x2"]:
        u = x - HS["x2"]
        r = math.sqrt(HS["R"] ** 2 - u * u)
        return HS["z_flat"] + HS["R"] - r, u / r, HS["R"] ** 2 / r**3
    return HS["z_flat"], 0.0, 0.0


def _point_mass_stop(x0, mu, centripetal=True, h=2e-5):
    """Where a point mass let go at x0 stops on the hockey stick under Coulomb friction μ with
    the full normal force m (g cos θ + v² κ) (``centripetal=False``: m g cos θ only, which is the
    energy line's assumption: it stops where z0 − z = μ (x − x0)). Euler in x on e = v²/2."""
    x, e = x0, 0.0
    while True:
        _, dz, d2 = _hockey_stick(x)
        sec = math.sqrt(1 + dz * dz)
        cos, sin = 1 / sec, -dz / sec
        kappa = d2 / sec**3 if centripetal else 0.0
        e += h * sec * (G * sin - mu * (G * cos + 2 * e * kappa))
        if e <= 0 and x > x0 + 10 * h:
            return x
        e = max(e, 0.0)
        x += h


@pytest.mark.parametrize("dx, transfer", [
    (0.01, "apic"),
    pytest.param(0.0075, "apic", marks=pytest.mark.slow),
    pytest.param(0.005, "pic", marks=pytest.mark.slow),
    pytest.param(0.005, "apic", marks=[pytest.mark.slow, pytest.mark.xfail(strict=True, reason=(
        "with APIC at dx = 0.005 the block stops 8.9 % of the travel short of the point mass (PIC at the "
        "same dx: -2.3 %); not analysed, like the AFLIP bounce of tests/test_physics.py"))]),
])
def test_a_block_on_a_hockey_stick_stops_where_a_sliding_point_mass_does(dx, transfer):
    """A thin elastic block (0.1 m × 0.02 m) let go on the 30° slope of a hockey stick (arc of
    radius 1 m into a flat floor, a polyline of 5 mm segments) with μ_w = 0.3 comes to rest
    (speed below 1 mm/s) where a point mass sliding with Coulomb friction stops: within 3 % of
    the travel (measured −1.4 % at dx = 0.01 with APIC, −2.5 % at 0.0075, −2.3 % at 0.005 with
    PIC). The energy line with slope μ_w, which leaves out the centripetal part of the normal
    force on the bend, puts the stop 7 % of the travel further (the point mass's own difference);
    the block is within 10 % of it (measured −8.5 % at dx = 0.01)."""
    mu, start, length, thick = 0.3, 0.15, 0.1, 0.02
    xs = np.arange(0.0, HS["x2"] + HS["flat"] + 1e-9, 0.005)
    terrain = jm.Terrain(tuple(xs), tuple(_hockey_stick(x)[0] for x in xs), friction="mu_w")
    loc, vol = jm.seed_box((0.0, 0.0), (length, thick), dx, 2)
    loc = np.asarray(loc)
    base = np.array([start, HS["z0"] - math.tan(THETA) * start])
    x = base + (loc[:, :1] - length / 2) * TANGENT + (0.5 * dx + loc[:, 1:]) * NORMAL
    origin = (-0.1, HS["z_flat"] - 0.1)
    cells = (math.ceil((xs[-1] + 0.1 - origin[0]) / dx), math.ceil((HS["z0"] + 0.2 - origin[1]) / dx))
    t_end = 2.0
    params = jm.Params.create(E=2e5, nu=0.3, rho=1550.0, mu_w=mu)
    grid = jm.Grid(cells, dx, origin=origin)
    budget = step_budget(jm.Config(grid=grid, t_end=t_end, max_steps=1).material, params, dx, t_end)
    cfg = jm.Config(grid=grid, t_end=t_end, max_steps=budget, walls=(terrain,), transfer=transfer,
                    frame_times=(t_end - 0.2, t_end))
    result = jm.simulate(cfg, jm.init_state(cfg, x, vol), params, observer=_mean)
    assert result.state.status == 0, result.status_text
    centre = np.asarray(result.frames["x"])
    assert np.linalg.norm(np.asarray(result.frames["v"])[-1]) < 1e-3  # at rest
    assert np.linalg.norm(centre[-1] - centre[0]) < 1e-3  # and it was 0.2 s before
    # The start and the stop as the centre's foot on the ground: x of the centre, less its
    # offset along the normal (on the slope; on the flat floor the normal is vertical).
    x0 = float(np.sum(x[:, 0] * np.asarray(vol)) / np.sum(vol)) - (0.5 * dx + thick / 2) * NORMAL[0]
    stop = float(centre[-1, 0])
    assert stop > HS["x2"], stop  # past the bend, on the flat floor
    exact = _point_mass_stop(x0, mu)
    energy_line = _point_mass_stop(x0, mu, centripetal=False)
    z_drop = _hockey_stick(x0)[0] - HS["z_flat"]
    assert abs(energy_line - (x0 + z_drop / mu)) < 1e-3  # the energy line, as its definition says
    travel = exact - x0
    assert abs(stop - exact) < 0.03 * travel, (stop, exact, travel)
    assert abs(stop - energy_line) < 0.10 * travel, (stop, energy_line, travel)
