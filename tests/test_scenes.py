"""Scene builders (docs/scenes.md) on tiny settings, and the differentiable observables."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm import scenes
from jaxmpm.observables import deposit_profile, front_position, particle_volumes
from jaxmpm.scenes import S1_DEPTH, S4_SIDE


# 40 s; every 2D scene runs by default through the command line (tests/test_cli.py), built from its file
# (tests/test_named_scenes.py)
@pytest.mark.slow
@pytest.mark.parametrize(
    "build",
    [
        lambda: scenes.gates_collapse(dx=0.02, t_end=0.02),
        lambda: scenes.slope_collapse(16.0, dx=0.04, t_end=0.02),
        lambda: scenes.cohesive_collapse(0.25, dx=0.03, t_end=0.02),
        lambda: scenes.aspect_ratio_collapse(2.0, dx=0.025, t_end=0.02),
        lambda: scenes.incline(26.0, dx=S1_DEPTH / 4, t_end=0.01),
        lambda: scenes.cohesive_collapse(0.0, dx=0.03, t_end=0.01, dim=3, width=0.06),
    ],
)
def test_scene_builds_and_runs(build):
    """Every builder runs without status bits. The column is the body [0, L] × [g, H + g] above
    the floor at y = 0, raised so that its lowest particle lies half a cell (0.501 dx) above
    the floor (g = wall_gap = (dx − dx/ppc)/2 for a lattice), and no particle's stencil reaches
    a node behind the floor, the back wall or a gate at t = 0 (docs/model.md §5; the scenes'
    placement convention). A 3D channel's side walls stand on the body's faces."""
    scene = build()
    config, state, params = scene
    x = np.asarray(state.x)
    gap, dx = scene.info.wall_gap, scene.info.dx
    np.testing.assert_allclose(x[:, 1].min(), 0.501 * dx, rtol=1e-12)
    if scene.info.sampling == "lattice":  # rows of spacing H / round(H ppc / dx)
        height = scene.info.height
        spacing = height / round(height * scene.info.ppc / dx)
        np.testing.assert_allclose(gap, 0.501 * dx - 0.5 * spacing, rtol=1e-9)
    assert x[:, 0].min() > 0 and x[:, 0].max() < scene.info.length and x[:, 1].max() < scene.info.height + gap
    assert _stencil_nodes_behind_walls(config, state) == 0
    result = jm.simulate(config, state, params)
    assert result.status == 0 and float(result.state.t) == config.t_end


def test_scene_info_is_one_typed_description():
    """Every scene describes itself with a SceneInfo: one name per fact (length, height, ...),
    None where a fact does not apply; to_dict() keeps the facts that apply, as JSON values."""
    import dataclasses
    import json

    column = scenes.aspect_ratio_collapse(2.0, dx=0.025, t_end=0.02)
    layer = scenes.incline(26.0, dx=S1_DEPTH / 4, t_end=0.01)
    block = scenes.falling_block(n_particles=64, t_end=0.01)
    assert (column.info.length, column.info.height, column.info.aspect) == (0.05, 0.1, 2.0)
    assert column.info.critical_start is None and column.info.width is None and column.info.side_gap > 0
    assert (layer.info.height, layer.info.length, layer.info.critical_start) == (0.038, 4 * 0.038 / 4, False)
    assert layer.info.aspect is None and layer.info.side_gap is None and layer.info.slope_deg == 26.0
    assert block.info.length == block.info.height == 0.5 and block.info.seed is None
    assert block.info.front0 == pytest.approx(float(np.asarray(block.state.x)[:, 0].max()) + block.info.dx / 4)
    out = column.info.to_dict()
    assert json.loads(json.dumps(out)) == out and "critical_start" not in out and out["aspect"] == 2.0
    assert isinstance(out["ppc"], int) and isinstance(out["particles_per_cell"], float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        column.info.length = 1.0
    with pytest.raises(ValueError, match="SceneInfo.dim"):
        dataclasses.replace(column.info, dim=4)
    with pytest.raises(ValueError, match="SceneInfo.dx"):
        dataclasses.replace(column.info, dx=0.0)


def _stencil_nodes_behind_walls(config, state):
    """How many (particle, stencil node) pairs have the node strictly behind a wall (within the
    wall's thickness and above a plate's lower edge) at t = 0. A 3D channel's side walls are left
    out: they stand on the body's faces, so that the channel is as wide as asked (a gap there
    widened it, and the column ended 3.8 % lower than in 2D: docs/validation.md §9)."""
    from jaxmpm.kernels import make_stencil

    nodes = config.grid.node_positions()[np.asarray(make_stencil(state.x, config.grid).index)]  # (S, N, dim)
    count = 0
    for wall in config.walls:
        if len(wall.normal) == 3 and wall.normal[2] != 0.0:
            continue
        signed = (nodes - np.asarray(wall.point)) @ np.asarray(wall.normal)
        behind = (signed < -1e-12) & (signed > -wall.thickness)
        if wall.edge is not None:
            behind &= (nodes - np.asarray(wall.point)) @ np.asarray(wall.edge) >= 0
        count += int(behind.sum())
    return count


def test_flush_bodies_weight_nodes_behind_the_floor():
    """wall_gap = 0 puts the body flush with the floor: its bottom row weights the nodes behind
    it, which the default half-cell gap avoids (the check above can fail)."""
    flush = scenes.cohesive_collapse(0.0, dx=0.03, t_end=0.02, wall_gap=0.0)
    assert _stencil_nodes_behind_walls(flush.config, flush.state) > 0
    with pytest.raises(ValueError, match="wall_gap"):
        scenes.cohesive_collapse(0.0, dx=0.03, wall_gap=-0.01)


def test_scene_parameters_follow_scenes_md():
    s4 = scenes.cohesive_collapse(0.25, dx=0.03, t_end=0.01)
    assert float(s4.params.beta) == 0.25 and float(s4.params.pc0) == 500.0 and float(s4.params.rho) == 1508.0
    s3 = scenes.slope_collapse(22.0, dx=0.04, t_end=0.01)
    g = np.asarray(s3.config.gravity)
    assert math.isclose(math.degrees(math.atan2(g[0], -g[1])), 22.0, abs_tol=1e-9)
    assert any(w.kind == "separable" and w.normal == (1.0, 0.0) for w in s3.config.walls)  # back wall
    with pytest.raises(ValueError, match="width"):
        scenes.cohesive_collapse(0.0, dim=3)
    with pytest.raises(ValueError, match="dx must be > 0"):
        scenes.gates_collapse(dx=-0.01)


def test_flow_reaching_the_grid_edge_sets_the_edge_bit():
    scene = scenes.cohesive_collapse(0.0, dx=S4_SIDE / 8, runout=0.03)
    result = jm.simulate(*scene, throw=False)
    assert result.status & jm.EDGE
    with pytest.raises(jm.SimulationError, match="edge of the grid"):
        jm.simulate(*scene)


def test_incline_starts_on_the_bagnold_profile():
    scene = scenes.incline(24.0, dx=S1_DEPTH / 8)
    z, v = np.asarray(scene.state.x[:, 1]) - scene.info.wall_gap, np.asarray(scene.state.v[:, 0])
    np.testing.assert_allclose(v, scenes.bagnold_velocity(z, 0.038, 24.0, scene.params), rtol=1e-6)
    # docs/model.md §6 worked example: v_max = 1.483 m/s at 24° for h = 0.038 m.
    assert abs(scenes.bagnold_velocity(0.038, 0.038, 24.0, scene.params) - 1.483) < 2e-3
    assert abs(scenes.bagnold_velocity(0.038, 0.038, 22.0, scene.params) - 0.433) < 2e-3
    with pytest.raises(ValueError, match="between atan"):
        scenes.bagnold_velocity(0.01, 0.038, 35.0, scene.params)


def test_observables_integrate_and_have_finite_gradients():
    """A uniform layer of height H gives h ≈ H inside and integrates to its area; the front is
    within a particle spacing of the last particle; gradients are finite, also where h = 0."""
    dx = 0.01
    x, vol = jm.seed_box((0.0, 0.0), (0.2, 0.05), dx, 2)
    x, vol = jnp.asarray(x), jnp.asarray(vol)
    xs = jnp.linspace(-0.1, 0.3, 801)
    h = deposit_profile(x, vol, xs, dx / 2)
    inside = (xs > 0.03) & (xs < 0.17)
    np.testing.assert_allclose(h[inside], 0.05, rtol=1e-3)
    np.testing.assert_allclose(jnp.sum(h) * (xs[1] - xs[0]), 0.2 * 0.05, rtol=1e-6)
    front = front_position(x, vol, sigma=dx / 8)
    assert abs(float(front) - float(x[:, 0].max())) < dx
    grads = jax.grad(lambda x: jnp.sum(deposit_profile(x, vol, xs, dx / 2) ** 2) + front_position(x, vol, dx / 8))(x)
    assert np.all(np.isfinite(grads))
    far = jax.grad(lambda x: deposit_profile(x, vol, jnp.asarray([5.0]), dx / 2)[0])(x)  # h = 0 there
    assert np.all(np.isfinite(far))
    state = jm.scenes.cohesive_collapse(0.0, dx=0.03, t_end=0.01).state
    np.testing.assert_allclose(particle_volumes(state), state.vol0)


def test_incline_critical_start_sets_pc_to_twice_the_lithostatic_pressure():
    """The critical start puts every particle on the apex of its ellipse at the lithostatic
    pressure (p_c = 2p for β = 0), through ε_v^p and the hardening law."""
    import math

    scene = jm.scenes.incline(24.0, dx=S1_DEPTH / 8, critical_start=True)
    params = scene.params
    z = np.asarray(scene.state.x[:, 1]) - scene.info.wall_gap
    p = float(params.rho) * 9.81 * math.cos(math.radians(24.0)) * (0.038 - z)
    pc = float(params.pc0) * np.exp(-float(params.xi) * np.asarray(scene.state.internal["eps_v_p"]))
    np.testing.assert_allclose(pc, 2.0 * p, rtol=1e-10)
    with pytest.raises(ValueError, match="xi > 0"):
        jm.scenes.incline(24.0, dx=S1_DEPTH / 8, critical_start=True, xi=0.0)


def test_profile_mirrored_at_the_back_face_reads_the_full_height_at_the_wall():
    """Without the mirror the kernel reads half the height at a wall (half of it lies behind the wall);
    mirrored at the body's back face it reads the height, and nothing behind the wall."""
    spacing = 0.001
    gx, gy = np.meshgrid(np.arange(0.5, 100) * spacing, np.arange(0.5, 50) * spacing, indexing="ij")
    x = jnp.asarray(np.stack([gx.ravel(), gy.ravel()], axis=1))
    vol = jnp.full(x.shape[0], spacing ** 2)
    xs = jnp.asarray([-0.002, 0.0, 0.05])
    plain = np.asarray(deposit_profile(x, vol, xs, 2 * spacing))
    mirrored = np.asarray(deposit_profile(x, vol, xs, 2 * spacing, mirror=0.0))
    np.testing.assert_allclose(plain[1:], [0.025, 0.05], rtol=0.02)
    np.testing.assert_allclose(mirrored, [0.0, 0.05, 0.05], rtol=0.02, atol=1e-12)
    assert scenes.cohesive_collapse(dx=S4_SIDE / 4).back_face == 0.0  # the wall plane sits 0.501 dx behind it
    assert scenes.gates_collapse(dx=0.004).back_face is None  # lifted gates, no wall to rest against
