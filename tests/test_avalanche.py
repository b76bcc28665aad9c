"""The S6 avalanche: the fields avalanche engineers use, checked on a layer whose
answers are known; the scene's set-up; the command line's quick run and its refusals."""

import json
import math

import numpy as np
import pytest
from helpers import cli, main_exit

import jaxmpm as jm
from jaxmpm.scenes.avalanche import SNOW, avalanche
from jaxmpm.studies.avalanche import path_fields


def _cli(*args, cwd=None):
    return cli("jaxmpm", *args, cwd=cwd)


def test_path_fields_of_a_known_layer():
    """A layer 1.2 m thick (normal to a 30° slope) from x = 100 to 200 m, moving at 10 m/s along
    the slope, then 20 m further on at 12 m/s: thickness 1.2 m inside it, speed 10 then 12 m/s,
    pressure ρu², the front at its lead bin, the runout at the farthest lead, the front speed
    and the momentum flux at a station."""
    theta = math.radians(30.0)
    terrain = jm.Terrain((0.0, 400.0), (400.0 * math.tan(theta), 0.0))
    along = np.array([math.cos(theta), -math.sin(theta)])
    spacing = 0.1
    s = np.arange(0.05, 100.0 / math.cos(theta), spacing)
    n = np.arange(0.05, 1.2, spacing)
    S, N = np.meshgrid(s, n, indexing="ij")
    base = np.stack([100.0 + S.ravel() * math.cos(theta), terrain.height(100.0) - S.ravel() * math.sin(theta)], -1)
    normal = np.array([math.sin(theta), math.cos(theta)])
    x0 = base + N.ravel()[:, None] * normal
    vol = np.full(len(x0), spacing * spacing)
    shift = 20.0 / math.cos(theta)
    x = np.stack([x0, x0 + shift * along])
    v = np.stack([np.broadcast_to(10.0 * along, x0.shape), np.broadcast_to(12.0 * along, x0.shape)])
    fields = path_fields(terrain, x, v, vol, np.array([1.0, 3.0]), rho=300.0, dx=1.0, station=150.0)
    inside = (fields.x > 110) & (fields.x < 190)
    np.testing.assert_allclose(fields.thickness[0, inside], 1.2, rtol=0.05)
    np.testing.assert_allclose(fields.speed[0, inside], 10.0, rtol=1e-9)
    np.testing.assert_allclose(fields.pressure_kpa[1, (fields.x > 130) & (fields.x < 210)], 300 * 144 / 1e3, rtol=1e-9)
    assert 196.0 <= fields.front[0] <= 200.0 and 216.0 <= fields.front[1] <= 220.0
    assert abs(fields.runout_x - fields.front[1]) < 1e-9
    np.testing.assert_allclose(fields.front_speed, 10.0, atol=2.0)  # 20 m in 2 s, to a bin
    assert abs(fields.force_kn_per_m[1] / (300 * 144 * 1.2 / 1e3) - 1) < 0.05
    summary = fields.summary()
    assert summary["runout_x"] == fields.runout_x and summary["peak_pressure_max_kpa"] == pytest.approx(43.2)


def test_avalanche_scene_set_up():
    """The ISeeSnow release: particles between x = 1045 and 1345 m, 1.5 m thick normal to the
    34° slope (its area 300 m / cos 34° × 1.5 m), on the shipped terrain, μ_w = 0.4."""
    scene = avalanche(dx=2.0, t_end=1.0, frames=2)
    config, state, params = scene
    x = np.asarray(state.x)
    assert x[:, 0].min() >= 1045.0 and x[:, 0].max() <= 1345.0
    area = float(np.sum(state.vol0))
    assert abs(area / (300.0 / math.cos(math.radians(34.0)) * 1.5) - 1) < 0.1, area
    ground = config.walls[0]
    assert isinstance(ground, jm.Terrain) and ground.friction == "mu_w" and float(params.mu_w) == pytest.approx(0.4)
    assert ground.x[0] == 1000.0 and ground.z[0] == 1500.0 and len(ground.x) == 1001
    assert config.active_nodes == 9 * state.n_particles and config.grid.n_nodes > 100 * config.active_nodes
    assert float(params.rho) == 300.0 and SNOW["wet"]["beta"] > 0
    with pytest.raises(ValueError, match="snow must be one of"):
        avalanche(snow="slush")
    with pytest.raises(ValueError, match="release must be an interval"):
        avalanche(release=(900.0, 1000.0))


def test_run_avalanche_quick_prints_the_fields(tmp_path):
    csv = tmp_path / "path.csv"
    out = _cli("run", "avalanche", "--quick", "--t-end", "8", "--json", "--no-progress", "--profile-csv", str(csv),
               "--station", "1351", "--obstacle", "3")
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    for key in ("runout_x", "front_speed_max", "peak_pressure_max_kpa", "peak_thickness_max", "peak_speed_max",
                "force_max_kn_per_m", "obstacle_force_max_kn_per_m", "n_particles", "n_steps", "status"):
        assert key in summary, key
    assert summary["station_x"] == 1351.0 and summary["obstacle_force_max_kn_per_m"] > 0
    assert summary["status"] == 0 and summary["runout_x"] > 1345.0 and summary["front_speed_max"] > 0
    lines = csv.read_text().splitlines()
    header = "x_m,z_m,peak_thickness_m,peak_speed_m_per_s,peak_pressure_kpa,deposit_m"
    assert header in lines
    rows = np.loadtxt(csv, delimiter=",", comments="#", skiprows=lines.index(header) + 1)
    assert rows.shape[1] == 6 and np.all(rows[:, 2] >= 0)


@pytest.mark.parametrize("args, message", [
    (("run", "avalanche", "--dim", "3"), "--dim does not apply to the avalanche"),
    (("run", "avalanche", "--ppc", "1.5"), "--ppc must be a positive integer"),
    (("run", "cohesive-collapse", "--terrain", "x.csv"), "--terrain applies to the avalanche scene"),
    (("run", "cohesive-collapse", "--obstacle", "5"), "--obstacle applies to the avalanche scene"),
    (("run", "avalanche", "--obstacle", "5"), "--obstacle needs --station"),
])
def test_run_avalanche_refuses_bad_options(args, message, capsys):
    code, err = main_exit("jaxmpm", (*args, "--no-progress"), capsys)  # in this process: no JAX import to wait for
    assert code == 2 and message in err, err


def test_run_avalanche_refuses_a_bad_terrain_file(tmp_path, capsys):
    bad = tmp_path / "terrain.csv"
    bad.write_text("x_m,z_m\n0,10\n0,5\n")
    code, err = main_exit("jaxmpm", ("run", "avalanche", "--terrain", bad, "--no-progress"), capsys)
    assert code == 2 and "Terrain.x must increase strictly" in err, err


@pytest.mark.slow  # 25 s; the terrain's mu_w gradient is checked against FD by default (test_terrain.py)
def test_gradient_of_the_travel_with_respect_to_mu_w_and_beta_matches_finite_differences():
    """Calibration on terrain: d(mean x of the snow after 1.5 s)/d(μ_w, β) through the avalanche
    (terrain contact, sparse grid, critical-state snow at β = 0.05), reverse mode against central
    differences in float64 (measured agreement 6e-6 and 2e-5 relative at 2 s)."""
    import jax
    import jax.numpy as jnp

    from jaxmpm.rollout import make_rollout

    config, state, params = avalanche(dx=2.0, t_end=1.5, frames=2, dtype=jnp.float64)
    rollout = make_rollout(config, observer=None)

    def travel(mu_w, beta):
        final = rollout(state, params.replace(mu_w=mu_w, beta=beta))[0]
        return jnp.sum(final.x[:, 0] * final.vol0) / jnp.sum(final.vol0)

    grad = jax.jit(jax.grad(travel, argnums=(0, 1)))(params.mu_w, jnp.float64(0.05))
    f = jax.jit(travel)
    h = 1e-5
    fd = ((f(params.mu_w + h, 0.05) - f(params.mu_w - h, 0.05)) / (2 * h),
          (f(params.mu_w, 0.05 + h) - f(params.mu_w, 0.05 - h)) / (2 * h))
    for g, d in zip(grad, fd):
        assert np.isfinite(g) and abs(g - d) < 1e-4 * abs(d), (grad, fd)
    assert grad[0] < 0  # more basal friction, less travel


def test_smooth_runout_of_a_known_layer():
    """A flat layer 1 m thick from x = 0 to 100 m, and a second one (a gap behind the front) from
    −40 to −20 m: the smoothed thickness is 1 m · ½ erfc((s − 100)/(w√2)) near the front; the
    smooth runout equals its definition on that exact thickness (quadrature), lies within w/5 of
    where it falls to 0.1 m (s = 100 + 1.2816 w), does not see the gap, a stray particle of
    1/10,000 of the snow 50 m ahead moves it by under 0.5 m, and moving every particle by δ moves it by δ (d runout/d
    shift = 1, to the sum's discretisation, by forward and reverse mode alike)."""
    import jax
    import jax.numpy as jnp

    from jaxmpm.studies.avalanche import smooth_runout

    terrain = jm.Terrain((-50.0, 300.0), (0.0, 0.0))
    spacing = 0.1
    X, Z = np.meshgrid(np.arange(0.5 * spacing, 100.0, spacing), np.arange(0.5 * spacing, 1.0, spacing))
    x = jnp.asarray(np.stack([X.ravel(), Z.ravel()], -1))
    vol = jnp.full(x.shape[0], spacing * spacing)
    xs = np.arange(50.0, 200.0, 0.25)
    width = 4 * 0.25
    r = float(smooth_runout(x, vol, terrain, xs))
    # the definition on the exact smoothed thickness, by fine quadrature
    from scipy.special import erfc, expit

    s = np.linspace(49.875, 199.875, 150_001)  # the points' cells: xs ± half a spacing
    floor = expit(-4.0)
    g = (expit((0.5 * erfc((s - 100.0) / (width * math.sqrt(2.0))) - 0.1) / 0.025) - floor) / (1.0 - floor)
    beyond = np.concatenate([np.cumsum((0.5 * (g[1:] + g[:-1]) * np.diff(s))[::-1])[::-1], [0.0]])
    assert abs(r - (s[0] + width + np.trapezoid(1.0 - np.exp(-beyond / width), s))) < 0.01, r
    assert abs(r - (100.0 + 1.2816 * width)) < 0.2 * width  # near the crossing h = 0.1 m
    gap = jnp.concatenate([x, x[(x[:, 0] < 20.0)] - jnp.array([60.0, 0.0])])
    wide = np.arange(-50.0, 200.0, 0.25)
    assert abs(float(smooth_runout(gap, jnp.full(gap.shape[0], spacing**2), terrain, wide)) - r) < 1e-6
    stray = jnp.concatenate([x, jnp.array([[150.0, 0.5]])])
    # its g (about 8e-3 m of "thick" ground) lifts 1 − exp(−C/w) by 8e-3 over the 50 m between: 0.38 m
    assert abs(float(smooth_runout(stray, jnp.append(vol, spacing**2), terrain, xs)) - r) < 0.5

    def shifted(delta):
        return smooth_runout(x + jnp.array([delta, 0.0]), vol, terrain, xs)

    # 1 to the cumulative sum's discretisation (points w/4 apart): measured 1 + 9e-4
    reverse, forward = float(jax.grad(shifted)(0.0)), float(jax.jvp(shifted, (0.0,), (1.0,))[1])
    assert abs(reverse - 1.0) < 2e-3 and abs(forward - reverse) < 1e-12
    with pytest.raises(ValueError, match="evenly spaced"):
        smooth_runout(x, vol, terrain, np.array([0.0, 1.0, 3.0]))


def test_obstacle_force_closes_the_momentum_balance():
    """A 3 m wall 6 m past the release: the snow hits it within 4 s; the impulses the terrain and
    the wall record close the momentum balance M v̄ = M g t − Σ impulse (float64), the wall is
    pushed downstream, and the force history is the impulse's change over each frame interval."""
    from jaxmpm.scenes.avalanche import OBSTACLE
    from jaxmpm.studies.avalanche import run_avalanche

    scene = avalanche(dx=2.0, t_end=4.0, frames=4, obstacle=(1351.0, 3.0))
    assert len(scene.config.walls) == 2 and scene.config.walls[OBSTACLE].normal == (-1.0, 0.0)
    result, fields = run_avalanche(scene)
    assert result.ok, result.status
    mass = np.asarray(scene.params.rho * scene.state.vol0)
    momentum = mass @ np.asarray(result.state.v)
    impulse = np.asarray(result.state.impulse)
    balance = momentum + impulse.sum(axis=0) - mass.sum() * 4.0 * np.array([0.0, -9.81])
    assert np.max(np.abs(balance)) < 1e-9 * mass.sum() * 9.81 * 4.0, balance
    assert impulse[OBSTACLE, 0] > 0 and fields.obstacle_force_kn_per_m[-1, 0] > 0
    times = np.asarray(scene.config.frame_times)
    np.testing.assert_allclose(np.sum(fields.obstacle_force_kn_per_m[:, 0] * np.diff(times, prepend=0.0)),
                               impulse[OBSTACLE, 0] / 1e3, rtol=1e-9)
    summary = fields.summary()
    assert summary["station_x"] == 1351.0 and summary["obstacle_force_max_kn_per_m"] > 0
    with pytest.raises(ValueError, match="obstacle station"):
        avalanche(dx=2.0, t_end=1.0, obstacle=(1000.0, 3.0))
    with pytest.raises(ValueError, match="obstacle height"):
        avalanche(dx=2.0, t_end=1.0, obstacle=(2000.0, -1.0))
