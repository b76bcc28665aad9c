"""Whole-simulation physics checks against closed-form solutions (docs/model.md §1 and §5).

Each test states its formula, the tolerance, and the value measured when the test was written
(float64, this code at the time of writing), so a reader can judge how much margin there is.
All scenes are 2D, Hencky-elastic, a few hundred particles at 2×2 per cell.

1. An elastic column settling under gravity in uniaxial strain (static Hencky solution).
2. A block on a tilted plane with Coulomb wall friction (slides at g(sin θ − μ cos θ), or sticks).
3. A gate: a plate that holds a block and releases material under its rising lower edge.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm

G = 9.81


def _positions(state, params):
    return state.x


def _centre_of_mass(state, params):
    """Mass-weighted mean position and velocity (particle mass = ρ V0, ρ uniform)."""
    w = state.vol0 / jnp.sum(state.vol0)
    return {"x": jnp.sum(w[:, None] * state.x, axis=0), "v": jnp.sum(w[:, None] * state.v, axis=0)}


def _max_steps(t_end, dx, params, n_frames, cfl_e=0.5):
    """Step budget: the elastic bound dt = cfl_e·dx/sqrt(E/ρ) governs here (speeds stay far below
    sqrt(E/ρ)); each output frame can add one clipped step."""
    dt = cfl_e * dx / math.sqrt(float(params.E) / float(params.rho))
    return int(math.ceil(1.05 * t_end / dt)) + n_frames + 10


# ---------------------------------------------------------------------------------------------
# 1. Elastic column under gravity, uniaxial strain

COLUMN_RHO, COLUMN_G, COLUMN_H, COLUMN_WIDTH, COLUMN_NU = 1000.0, 10.0, 0.5, 0.2, 0.3
COLUMN_M = 5.0e5  # constrained modulus λ + 2G; ρ g H / M = 1 % strain at the base
COLUMN_E = COLUMN_M * (1 + COLUMN_NU) * (1 - 2 * COLUMN_NU) / (1 - COLUMN_NU)


def _column_strain(Y):
    """Hencky strain ε(Y) < 0 solving M ε exp(−ε) = −ρ g (H − Y) (Newton; converges from ε = s)."""
    s = -COLUMN_RHO * COLUMN_G * (COLUMN_H - np.asarray(Y, float)) / COLUMN_M
    eps = s.copy()
    for _ in range(30):
        eps = eps - (eps * np.exp(-eps) - s) / ((1.0 - eps) * np.exp(-eps))
    return eps, s


def column_displacement(Y):
    """Static vertical displacement u(Y) = ∫_0^Y (exp(ε(Y')) − 1) dY' of the column.

    With s(Y) = ε e^{−ε} = −ρ g (H − Y)/M, dY = (M/ρg) (1 − ε) e^{−ε} dε, so the integral is
    (M/ρg) ∫ (1 − ε)(1 − e^{−ε}) dε = (M/ρg) [ε − ε²/2 − ε e^{−ε}] = (M/ρg) [ε − ε²/2 − s],
    taken between ε(0) and ε(Y).
    """
    eps, s = _column_strain(Y)
    eps0, s0 = _column_strain(0.0)
    prim = lambda e, s: e - 0.5 * e * e - s  # noqa: E731
    return COLUMN_M / (COLUMN_RHO * COLUMN_G) * (prim(eps, s) - prim(eps0, s0))


def test_column_displacement_closed_form_matches_quadrature():
    """The closed form of u(Y) against a trapezoid quadrature of exp(ε) − 1 (rtol 1e-8)."""
    Y = np.linspace(0.0, COLUMN_H, 200001)
    integrand = np.exp(_column_strain(Y)[0]) - 1.0
    quad = np.concatenate([[0.0], np.cumsum(0.5 * (integrand[1:] + integrand[:-1]) * np.diff(Y))])
    np.testing.assert_allclose(column_displacement(Y[::1000]), quad[::1000], rtol=1e-8, atol=1e-14)


def _settle_column(dx, t_end, n_frames=200):
    """Release a stress-free column on a no-slip floor between frictionless separable walls
    under gravity with PIC transfer; return reference heights Y, vertical displacements per
    frame (n_frames, N), the frame times and the final state."""
    floor, left = 2 * dx, 2 * dx
    right = left + COLUMN_WIDTH
    cells = (round((COLUMN_WIDTH + 4 * dx) / dx), round((1.1 * COLUMN_H + 4 * dx) / dx))
    walls = (
        jm.Wall((0.0, floor), (0.0, 1.0), kind="no-slip"),
        jm.Wall((left, 0.0), (1.0, 0.0), kind="separable"),
        jm.Wall((right, 0.0), (-1.0, 0.0), kind="separable"),
    )
    params = jm.Params.create(E=COLUMN_E, nu=COLUMN_NU, rho=COLUMN_RHO)
    frame_times = tuple(np.linspace(t_end / n_frames, t_end, n_frames))
    cfg = jm.Config(
        grid=jm.Grid(cells, dx), t_end=t_end, max_steps=_max_steps(t_end, dx, params, n_frames),
        walls=walls, gravity=(0.0, -COLUMN_G), transfer="pic", frame_times=frame_times,
    )
    x, vol = jm.seed_box((left, floor), (right, floor + COLUMN_H), dx, 2)
    result = jm.simulate(cfg, jm.init_state(cfg, x, vol), params, observer=_positions)
    X = np.asarray(result.frames)
    return x[:, 1] - floor, X[:, :, 1] - x[None, :, 1], np.asarray(frame_times), result.state


def _column_errors(dx, t_end):
    """Relative errors of the late-time-averaged (t ≥ t_end/2) mean displacement, top-layer
    displacement and interior compression (top layer minus the layer nearest Y = H/4), and the
    final τ_xx/τ_yy summed over particles."""
    Y, uy, t, state = _settle_column(dx, t_end)
    late = t >= 0.5 * t_end
    u_exact = column_displacement(Y)
    layers = np.unique(Y)
    top = Y == layers[-1]
    ref = Y == layers[np.argmin(np.abs(layers - 0.25 * COLUMN_H))]
    mean = uy[late].mean(axis=1).mean() / u_exact.mean() - 1.0
    top_err = uy[late][:, top].mean() / u_exact[top].mean() - 1.0
    compression = uy[late][:, top].mean() - uy[late][:, ref].mean()
    compression_err = compression / (u_exact[top].mean() - u_exact[ref].mean()) - 1.0
    tau = np.asarray(state.tau)
    lateral = tau[:, 0, 0].sum() / tau[:, 1, 1].sum()
    return mean, top_err, compression_err, lateral


@pytest.mark.slow  # 7 s: a physics check at scale (the static column against Hencky)
def test_elastic_column_settles_to_static_hencky_solution():
    """Uniaxial-strain column of height H = 0.5 m, width 0.2 m, ρ = 1000, g = 10, ν = 0.3,
    M = λ + 2G = 5e5 Pa (base strain ≈ −1 %), released stress-free under gravity.

    Static solution (2D Hencky, lateral strain zero): Cauchy σ_yy(Y) = −ρ g (H − Y) exactly (mass
    conservation), τ_yy = J σ_yy with J = e^ε, τ_yy = M ε, so M ε e^{−ε} = −ρ g (H − Y), and
    u(Y) = ∫_0^Y (e^{ε} − 1) dY' (closed form in ``column_displacement``). PIC damps the
    oscillation set off by the sudden load only slowly, so displacements are averaged over the
    second half of the run (≥ 16 periods 4H/c of the fundamental mode), which removes the
    oscillation to well under 1 % of the static value.

    Checked at dx = 0.05 and 0.025 (10 and 20 cells over H):
    - lateral strain zero: Σ τ_xx / Σ τ_yy = λ/(λ + 2G) = ν/(1 − ν) within 1 % (measured
      0.6 % and 0.4 %: the nodes on the walls let the column widen by ε_xx ≈ +2e-5);
    - interior compression u(top) − u(H/4), free of the floor's boundary layer: within 2 % at
      dx = 0.05 and 1 % at dx = 0.025 (measured 1.1 % and 0.5 %);
    - mean and top-surface displacement: the grid-node no-slip condition is first order (the
      B-spline field is not zero at the material surface Y = 0 and the first cell is too soft),
      so MPM is too compliant by about dx/H: measured 8.9 % → 4.6 % (mean) and 6.4 % → 3.4 %
      (top). The fitted order log2(e(dx)/e(dx/2)) must lie in [0.75, 1.25] (measured 0.97,
      0.94), and the Richardson extrapolation 2 u(dx/2) − u(dx) must match the analytic value
      within 1 % (measured 0.2 % and 0.3 %).
    """
    coarse = _column_errors(0.05, 3.0)
    fine = _column_errors(0.025, 5.0)
    ratio = COLUMN_NU / (1 - COLUMN_NU)
    for errors in (coarse, fine):
        assert abs(errors[3] / ratio - 1.0) < 0.01, errors
    assert abs(coarse[2]) < 0.02, coarse
    assert abs(fine[2]) < 0.01, fine
    for name, e_coarse, e_fine in (("mean", coarse[0], fine[0]), ("top", coarse[1], fine[1])):
        assert e_coarse > 0 and e_fine > 0, (name, e_coarse, e_fine)
        order = math.log2(e_coarse / e_fine)
        assert 0.75 <= order <= 1.25, (name, e_coarse, e_fine, order)
        assert abs(2 * e_fine - e_coarse) < 0.01, (name, e_coarse, e_fine)


# ---------------------------------------------------------------------------------------------
# 2. Coulomb friction on a tilted plane

SLOPE_DEG = 30.0  # tan θ = 0.577


def _slide(mu, transfer="pic", t_end=0.4, dx=0.025, n_frames=100, gap=None, kind="non-separable"):
    """An elastic block (0.2 m × 0.1 m, E = 1e6, ν = 0.3, ρ = 1550) released at rest on a
    non-separable floor (the reference code's slip-stick: friction on every contact node) with
    friction ``mu`` under g = 9.81 (sin θ, −cos θ), its lower face ``gap`` above it (default: the
    scenes' convention, the lowest particle row 0.501 dx above the floor, gap = 0.251 dx for
    2 × 2 per cell). Returns frame times and the centre of mass's displacement and velocity per
    frame."""
    gap = 0.501 * dx - 0.25 * dx if gap is None else gap
    theta = math.radians(SLOPE_DEG)
    floor, start, length, height = 2 * dx, 3 * dx, 0.2, 0.1
    travel = 0.5 * G * math.sin(theta) * t_end**2
    cells = (math.ceil((start + length + travel + 4 * dx) / dx), math.ceil((height + 5 * dx) / dx))
    params = jm.Params.create(E=1e6, nu=0.3, rho=1550.0)
    frame_times = tuple(np.linspace(t_end / n_frames, t_end, n_frames))
    cfg = jm.Config(
        grid=jm.Grid(cells, dx), t_end=t_end, max_steps=_max_steps(t_end, dx, params, n_frames),
        walls=(jm.Wall((0.0, floor), (0.0, 1.0), kind=kind, friction=mu),),
        gravity=(G * math.sin(theta), -G * math.cos(theta)), transfer=transfer,
        frame_times=frame_times,
    )
    x, vol = jm.seed_box((start, floor + gap), (start + length, floor + gap + height), dx, 2)
    state0 = jm.init_state(cfg, x, vol)
    result = jm.simulate(cfg, state0, params, observer=_centre_of_mass)
    com0 = np.average(x, axis=0, weights=vol)
    frames = result.frames
    return np.asarray(frame_times), np.asarray(frames["x"]) - com0, np.asarray(frames["v"])


@pytest.mark.parametrize("mu", [0.3, 0.5])
def test_block_slides_down_slope_at_coulomb_acceleration(mu):
    """μ_w < tan θ (θ = 30°): the block slides with a = g (sin θ − μ_w cos θ) (2.356 and
    0.657 m/s² for μ_w = 0.3, 0.5). a is the slope of a straight-line fit of the centre-of-mass
    velocity over t ∈ [0.1, 0.4] s, after the transient of the sudden load (the elastic wave
    crosses the 0.1 m block in ~4 ms). Tolerance 1 % of a (measured ≤ 1e-4 relative; even at
    μ_w = 0.57, 1 % below tan θ, it was 8e-4). The block stays on the floor: |Δy_c| < 0.01 dx
    (measured max 7e-5 m ≈ 0.003 dx, the elastic compression and its oscillation).

    PIC transfer: see ``test_block_slides_with_aflip_transfer`` for AFLIP.
    """
    t, com, vel = _slide(mu)
    theta = math.radians(SLOPE_DEG)
    expected = G * (math.sin(theta) - mu * math.cos(theta))
    window = t >= 0.1
    accel = np.polyfit(t[window], vel[window, 0], 1)[0]
    assert abs(accel / expected - 1.0) < 0.01, (accel, expected)
    assert np.max(np.abs(com[:, 1])) < 0.01 * 0.025, com[:, 1]


def test_block_sticks_when_friction_exceeds_slope():
    """μ_w = 0.7 > tan θ = 0.577: static friction holds the block. Over 0.4 s its centre of mass
    moves less than 1 % of the frictionless slide distance g sin θ t²/2 = 0.39 m (measured
    2.9e-4 m, 0.075 %: the elastic shear of the block and the first few steps before the normal
    contact force builds up), and the final speed is below 1e-3 of g sin θ t = 1.96 m/s
    (measured 2e-8 m/s). PIC transfer."""
    t, com, vel = _slide(0.7)
    theta = math.radians(SLOPE_DEG)
    assert abs(com[-1, 0]) < 0.01 * 0.5 * G * math.sin(theta) * t[-1] ** 2, com[-1]
    assert abs(vel[-1, 0]) < 1e-3 * G * math.sin(theta) * t[-1], vel[-1]


AFLIP_KNOWN_FAILURE = pytest.mark.xfail(
    strict=True, reason="known limitation: with AFLIP the block slides 40 % too fast at mu_w = 0.5 and dx = 0.0125 "
    "while it bounces off the floor by half a cell (see test_aflip_block_stays_on_floor_and_sticks)")


# The known failure at dx = 0.0125 (12 s) is recorded in the slow set.
@pytest.mark.parametrize("mu, dx", [(0.3, 0.025), (0.5, 0.025),
                                    pytest.param(0.5, 0.0125, marks=[pytest.mark.slow, AFLIP_KNOWN_FAILURE])])
def test_block_slides_with_aflip_transfer(mu, dx):
    """The sliding acceleration of ``test_block_slides_down_slope_at_coulomb_acceleration`` with
    the default AFLIP transfer (α = 0.95) and the reference code's non-separable rule (friction
    on every contact node), the block's lowest particles half a cell above the floor: a = g (sin θ
    − μ_w cos θ) within 1 % (measured −0.05 % at μ_w = 0.3, +0.45 % at μ_w = 0.5, dx = 0.025; at
    dx = 0.0125, +0.04 % and +40 %, the strict xfail). With the block flush on the floor (gap 0)
    the same rule slid at 0.73 m/s² instead of 2.36 (μ_w = 0.3): the bottom particles' stencils
    reach the nodes behind the floor, whose extrapolated outward velocity the rule charges with
    friction. The half-cell start removes that (docs/model.md §5)."""
    t, com, vel = _slide(mu, transfer="aflip", dx=dx)
    theta = math.radians(SLOPE_DEG)
    expected = G * (math.sin(theta) - mu * math.cos(theta))
    window = t >= 0.1
    accel = np.polyfit(t[window], vel[window, 0], 1)[0]
    assert abs(accel / expected - 1.0) < 0.01, (accel, expected)


@pytest.mark.xfail(
    strict=True,
    reason="known limitation: with AFLIP an elastic block on a frictional slope bounces (its centre rises by "
    "0.07-0.16 dx at dx = 0.025, up to 0.47 dx at 0.0125) and, above tan θ, creeps (2.5 cm in 0.4 s, 6 % of the "
    "free slide); PIC is exact. The half-cell start did not remove it",
)
def test_aflip_block_stays_on_floor_and_sticks():
    """AFLIP version of the no-lift and sticking checks (|Δy_c| < 0.01 dx while sliding at
    μ_w = 0.3; centre-of-mass shift < 1 % of the free slide at μ_w = 0.7), with the block's lowest
    particles half a cell above the floor and the non-separable rule. Measured: rise 1.8 mm
    (0.07 dx) at μ_w = 0.3, 3.3 mm at 0.5, 4.0 mm at 0.7 (5.9 mm, 0.47 dx, at dx = 0.0125 and
    μ_w = 0.5); creep 2.5 cm at μ_w = 0.7 (2.7 cm at dx = 0.0125). The rise does not shrink with
    dx: it is the block's elastic release (F_e = I under gravity) kept undamped by the FLIP part,
    with the frictional grid correction acting only while it presses on the floor."""
    t, com, vel = _slide(0.3, transfer="aflip")
    assert np.max(np.abs(com[:, 1])) < 0.01 * 0.025, np.max(np.abs(com[:, 1]))
    t, com, vel = _slide(0.7, transfer="aflip")
    theta = math.radians(SLOPE_DEG)
    assert abs(com[-1, 0]) < 0.01 * 0.5 * G * math.sin(theta) * t[-1] ** 2, com[-1]


# ---------------------------------------------------------------------------------------------
# 3. A gate: hold, then release under the rising lower edge

GATE_DX = 0.025


def _gate_run(lift_speed, t_end, E=1e6, height=0.1, length=0.2, n_frames=60, transfer="aflip"):
    """A block of ``length`` × ``height`` resting on a frictionless non-separable floor (μ_w = 0)
    on a 30° slope, its downhill face on a separable gate at x_g that rises at ``lift_speed``.
    Returns frame times, positions per frame, initial positions, x_g and the floor height."""
    dx = GATE_DX
    theta = math.radians(SLOPE_DEG)
    floor, start = 2 * dx, 3 * dx
    x_gate = start + length
    travel = 0.5 * G * math.sin(theta) * t_end**2
    cells = (math.ceil((x_gate + travel + 6 * dx) / dx), math.ceil((height + 6 * dx) / dx))
    walls = (
        jm.Wall((0.0, floor), (0.0, 1.0), kind="non-separable", friction=0.0),
        jm.Wall(point=(x_gate, floor), normal=(-1.0, 0.0), kind="separable",
                velocity=(0.0, lift_speed), edge=(0.0, 1.0), thickness=2 * dx),
    )
    params = jm.Params.create(E=E, nu=0.3, rho=1550.0)
    frame_times = tuple(np.linspace(t_end / n_frames, t_end, n_frames))
    cfg = jm.Config(
        grid=jm.Grid(cells, dx), t_end=t_end, max_steps=_max_steps(t_end, dx, params, n_frames),
        walls=walls, gravity=(G * math.sin(theta), -G * math.cos(theta)), transfer=transfer,
        frame_times=frame_times,
    )
    x, vol = jm.seed_box((start, floor), (x_gate, floor + height), dx, 2)
    result = jm.simulate(cfg, jm.init_state(cfg, x, vol), params, observer=_positions)
    return np.asarray(frame_times), np.asarray(result.frames), x, x_gate, floor


def test_static_gate_holds_block():
    """U = 0: the gate (separable plate, normal −x) holds a stiff block (E = 1e6) that gravity
    along the 30° slope presses against it. Over 0.3 s no particle crosses x_g (measured: the
    front particles stay dx/4 behind it, where they were seeded) and the centre of mass moves
    less than 0.5 % of the free-slide distance g sin θ t²/2 = 0.22 m (measured 1.4e-4 m, 0.06 %)."""
    t, X, x0, x_gate, _ = _gate_run(0.0, 0.3)
    assert X[:, :, 0].max() < x_gate, X[:, :, 0].max() - x_gate
    drift = X[:, :, 0].mean(axis=1) - x0[:, 0].mean()
    free_slide = 0.5 * G * math.sin(math.radians(SLOPE_DEG)) * t[-1] ** 2
    assert np.max(np.abs(drift)) < 0.005 * free_slide, drift


def test_lifted_gate_releases_block():
    """U = 2 m/s, stiff block of height h = 0.1 m. While the lower edge is below the block's top
    (t ≤ h/U) no particle crosses x_g: the plate still covers the upper part of the face and the
    stiff block cannot squeeze under. Once the edge has cleared the top and the stencil of the
    top particles (t ≥ (h + 2 dx)/U, plus 30 ms), the block slides freely: the centre-of-mass
    acceleration, fitted to its displacement, equals g sin θ = 4.905 m/s² within 1 % (measured
    1e-12 relative: frictionless floor, no residual gate contact), and by t = 0.3 s most of the
    block (measured 81 %) is past x_g; required > 50 %."""
    lift, height, t_end = 2.0, 0.1, 0.3
    t, X, _, x_gate, _ = _gate_run(lift, t_end, height=height)
    covered = t <= height / lift
    assert X[covered, :, 0].max() < x_gate, X[covered, :, 0].max() - x_gate
    free = t >= (height + 2 * GATE_DX) / lift + 0.03
    accel = 2.0 * np.polyfit(t[free], X[free, :, 0].mean(axis=1), 2)[0]
    expected = G * math.sin(math.radians(SLOPE_DEG))
    assert abs(accel / expected - 1.0) < 0.01, (accel, expected)
    assert np.mean(X[-1, :, 0] > x_gate) > 0.5


@pytest.mark.slow  # 17 s: a physics check at scale; the lifted and the static gate run by default
def test_partly_lifted_gate_lets_soft_material_pass_only_below_its_edge():
    """A soft block (E = 2e4, 0.2 m × 0.2 m; ρ g h / E ≈ 15 % strain) behind a gate rising slowly
    (U = 0.2 m/s, edge at 0.12 m after 0.6 s, below the block's top at ≈ 0.19 m). The plate acts
    on grid nodes at or above its lower edge, so at every frame each particle past x_g must lie
    below edge(t) + dx (one cell for the support of the node stencil; measured ≤ 0.44 dx), i.e.
    material held above the edge never crosses. Material does flow out under the edge: more than
    2 % of the particles are past x_g at t = 0.6 s (measured 8 %)."""
    lift, t_end = 0.2, 0.6
    t, X, _, x_gate, floor = _gate_run(lift, t_end, E=2e4, height=0.2, length=0.2, n_frames=50)
    edge = floor + lift * t
    past = X[:, :, 0] > x_gate
    height_over_edge = np.where(past, X[:, :, 1] - edge[:, None], -np.inf)
    assert height_over_edge.max() < GATE_DX, height_over_edge.max() / GATE_DX
    assert np.mean(past[-1]) > 0.02, np.mean(past[-1])
