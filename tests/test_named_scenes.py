"""The named collapses (S2–S5, S7) are their shipped experiment files (jaxmpm.scenes.named): the
builders, ``build_scene`` and ``named_experiment(...).scene()`` make the same scene, and that scene
is what the file's own numbers say (the expectations below are computed from the file, not from a
stored copy of a scene). Small grids throughout: nothing here runs a simulation."""

import math

import numpy as np
import pytest

from jaxmpm import scenes
from jaxmpm.experiment import SHIPPED_EXPERIMENTS, shipped_experiment
from jaxmpm.scenes import build_scene, named_experiment

BUILDERS = {"gates-collapse": scenes.gates_collapse, "slope-collapse": scenes.slope_collapse,
            "cohesive-collapse": scenes.cohesive_collapse, "aspect-ratio": scenes.aspect_ratio_collapse,
            "aluminium-bars": scenes.aluminium_bars}
G = 9.81


def _same_scene(a, b):
    assert a.name == b.name and a.config == b.config and a.info == b.info
    for field in ("x", "v", "F", "C", "tau", "vol0"):
        np.testing.assert_array_equal(np.asarray(getattr(a.state, field)), np.asarray(getattr(b.state, field)))
    assert a.params.to_dict() == b.params.to_dict()


def _side_gap(extent, dx):
    """The gap each side of a body between two walls that both lie on node rows, at least 0.501 dx."""
    cells = math.ceil((extent + 2 * 0.501 * dx) / dx - 1e-9)
    return 0.5 * (cells * dx - extent)


@pytest.mark.parametrize("name", sorted(SHIPPED_EXPERIMENTS))
def test_a_named_scene_is_what_its_file_says(name):
    """Built at a coarse grid on a 2 x 2 lattice: the column, bed, walls, gates, end time, material
    and grid reach are the shipped file's numbers."""
    e = shipped_experiment(name)
    dx = min(e.length, e.height) / 4
    scene = BUILDERS[name](dx=dx, ppc=2, sampling="lattice", dtype="float64")
    config, state, params = scene
    # the column and its facts
    info = scene.info
    assert (info.length, info.height, info.slope_deg, info.dx, info.ppc) == (e.length, e.height, e.slope, dx, 2)
    assert info.aspect == (e.height / e.length if name == "aspect-ratio" else None)
    x = np.asarray(state.x)
    counts = [round(e.length * 2 / dx), round(e.height * 2 / dx)]
    assert len(x) == counts[0] * counts[1]
    np.testing.assert_allclose(float(np.sum(state.vol0)), e.length * e.height, rtol=1e-12)
    np.testing.assert_allclose(x[:, 1].min(), 0.501 * dx, rtol=1e-12)
    assert 0 < x[:, 0].min() and x[:, 0].max() < e.length
    # the end time, the bed's slope, and when the column is at rest
    assert config.t_end == e.t_end and config.frame_times == ()
    theta = math.radians(e.slope)
    assert config.gravity == (G * math.sin(theta), -G * math.cos(theta))
    assert config.rest_speed == 0.005 * math.sqrt(G * e.height)
    assert config.rest_duration == 0.25 * math.sqrt(e.height / G)
    assert (config.transfer, config.alpha, config.cfl) == (e.transfer, e.alpha, e.cfl)
    # the bed, the back wall and the gates
    floor, *others = config.walls
    assert floor.point == (0.0, 0.0) and floor.normal == (0.0, 1.0) and floor.kind == e.floor
    front_speed, back_speed = e.gate_speeds
    gap = _side_gap(e.length, dx) if front_speed is not None and (e.back_wall or back_speed is not None) \
        else 0.501 * dx
    expected = []
    if back_speed is not None or e.back_wall:
        expected.append(((-gap, 0.0), (1.0, 0.0), (0.0, back_speed or 0.0)))
    if front_speed is not None:
        expected.append(((e.length + gap, 0.0), (-1.0, 0.0), (0.0, front_speed)))
    assert [(w.point, w.normal, w.velocity) for w in others] == expected
    assert all(w.kind == "separable" for w in others)
    # the grid reaches the file's runout and three cells beyond the column (and behind it, for a
    # back gate), to the next node; aspect-ratio's runout holds four cells, of the grid it is on
    grid = config.grid
    x_lo, x_hi = grid.origin[0], grid.origin[0] + grid.cells[0] * grid.dx
    runout = e.runout + (4 * dx - 4 * e.dx if name == "aspect-ratio" else 0.0)
    reach, behind = e.length + gap + runout + 3 * dx, gap + (e.backward_runout or 0.0) + 3 * dx
    assert reach - 1e-12 <= x_hi < reach + dx
    assert -behind - dx - 1e-12 <= x_lo <= -behind + 1e-12
    # the material
    got = params.to_dict()
    assert {k: got[k] for k in e.material} == dict(e.material)


OPTIONS = [
    {},
    {"ppc": 2, "sampling": "lattice"},
    {"seed": 3, "t_end": 0.2, "frames": 4, "values": {"beta": 0.2, "mu1": 0.4}},
    {"dim": 3, "dtype": "float64"},  # width: three cells (a 3D channel is a whole number of cells wide)
]


@pytest.mark.parametrize("options", OPTIONS)
@pytest.mark.parametrize("name", sorted(SHIPPED_EXPERIMENTS))
def test_builder_build_scene_and_named_experiment_agree(name, options):
    e = shipped_experiment(name)
    options = {"dx": min(e.length, e.height) / 3, **options}
    if options.get("dim") == 3:
        options["width"] = 3 * options["dx"]
    values = options.pop("values", {})
    scene = build_scene(name, values=values, **options)
    _same_scene(scene, named_experiment(name, values=values, **options).scene())
    _same_scene(scene, BUILDERS[name](**options, **values))
    assert scene.experiment is not None and scene.experiment.name == name


@pytest.mark.parametrize("slope, t_end", [(-5.0, 1.0), (0.0, 1.0), (10.0, 1.0), (14.9, 1.0), (15.0, 1.5), (25.0, 1.5)])
def test_the_slope_family(slope, t_end):
    e = shipped_experiment("slope-collapse")
    member = named_experiment("slope-collapse", slope=slope)
    assert (member.slope, member.t_end) == (slope, t_end)
    assert member.runout == pytest.approx(2 * 1.2 * e.height * (1 + max(slope, 0.0) / 8), rel=1e-12)
    assert member.replace(slope=e.slope, t_end=e.t_end, runout=e.runout) == e  # nothing else changes
    scene = build_scene("slope-collapse", slope=slope, dx=0.04)
    _same_scene(scene, scenes.slope_collapse(slope, dx=0.04))
    assert scene.info.slope_deg == slope and scene.config.t_end == t_end
    assert named_experiment("slope-collapse", slope=slope, t_end=0.3).t_end == 0.3  # an option over the rule


@pytest.mark.parametrize("a", [0.5, 1.0, 2.0, 3.0, 6.0])
def test_the_aspect_ratio_family(a):
    e = shipped_experiment("aspect-ratio")
    member = named_experiment("aspect-ratio", aspect=a)
    law = 1.2 * a if a <= 2.3 else 1.9 * a ** (2 / 3)
    assert (member.length, member.height, member.aspect, member.dx) == (e.length, a * e.length, a, e.dx)
    assert member.t_end == pytest.approx(4 * math.sqrt(a * e.length / G) + 0.1, rel=1e-12)
    assert member.runout == pytest.approx(1.6 * law * e.length + 4 * e.dx, rel=1e-12)
    scene = member.scene()
    assert scene.info.aspect == a and scene.info.height == a * e.length
    _same_scene(scene, scenes.aspect_ratio_collapse(a))
    coarse = named_experiment("aspect-ratio", aspect=a, dx=0.01)
    assert coarse.runout == pytest.approx(1.6 * law * e.length + 4 * 0.01, rel=1e-12)


def test_each_family_file_is_its_default_member():
    """The shipped S3 and S5 files are the members the rules make at their own slope and aspect
    ratio: the rule and the file agree on the end time and the grid's reach."""
    for name in ("slope-collapse", "aspect-ratio"):
        assert named_experiment(name) == shipped_experiment(name)
    assert named_experiment("slope-collapse").slope == 10.0 and named_experiment("aspect-ratio").aspect == 1.0


def test_another_column_length_keeps_the_cells_per_length():
    e = shipped_experiment("aspect-ratio")
    scene = scenes.aspect_ratio_collapse(2.0, L0=2 * e.length)
    assert scene.info.length == 2 * e.length and scene.info.height == 4 * e.length and scene.info.aspect == 2.0
    assert scene.info.dx == pytest.approx(2 * e.dx, rel=1e-12)


@pytest.mark.parametrize("call, message", [
    (lambda: named_experiment("elastic-block"), "elastic-block is not a collapse"),
    (lambda: named_experiment("avalanche"), "name must be one of the named collapses"),
    (lambda: named_experiment("cohesive-collapse", slope=5.0), "--slope applies to slope-collapse, not cohesive"),
    (lambda: named_experiment("slope-collapse", aspect=2.0), "--aspect applies to aspect-ratio, not slope-collapse"),
    (lambda: named_experiment("aspect-ratio", aspect=-1.0), "aspect must be > 0, got -1.0"),
    (lambda: named_experiment("aspect-ratio", dim=3), r"width \(the channel width, m\) is required when dim=3"),
    (lambda: named_experiment("slope-collapse", dx=-0.01), "dx must be > 0 m, got -0.01"),
    (lambda: named_experiment("slope-collapse", slope=70.0), r"slope must be in \(-60, 60\) degrees, got 70.0"),
    (lambda: named_experiment("aspect-ratio", aspect=2.0, dx=0.2), "dx must be at most the column's thinnest side"),
    (lambda: named_experiment("gates-collapse", values={"nu": 0.7}), r"nu must be in \(-1, 0.5\)"),
    (lambda: named_experiment("gates-collapse", t_end=-1.0), "t_end must be > 0 s, got -1.0"),
    (lambda: build_scene("nope"), "scene must be one of"),
    (lambda: build_scene("elastic-block", slope=3.0), "--slope applies to slope-collapse, not elastic-block"),
    (lambda: scenes.aspect_ratio_collapse(-1.0), "a must be > 0, got -1.0"),
    (lambda: scenes.aluminium_bars(dx=-0.01), "dx must be > 0, got -0.01"),
])
def test_bad_options_are_refused_naming_the_option(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_elastic_block_is_still_a_named_scene():
    block = build_scene("elastic-block", t_end=0.01)
    assert block.name == "elastic-block" and block.experiment is None and block.info.sampling == "lattice"


def test_derived_scenes_keep_the_named_scene():
    """at_dx (calibration's grid term), resampled (its sampling term) and variant (its designer)
    on scenes built from the files: the same as building the changed scene directly."""
    L = scenes.S4_SIDE
    scene = build_scene("cohesive-collapse", dx=L / 4, t_end=0.2, values={"beta": 0.2})
    _same_scene(scene.at_dx(L / 3), scenes.cohesive_collapse(0.2, dx=L / 3, t_end=0.2))
    np.testing.assert_array_equal(np.asarray(scene.resampled(5).x),
                                  np.asarray(scenes.cohesive_collapse(0.2, dx=L / 4, t_end=0.2, seed=5).state.x))
    taller = scene.variant(height=0.06, slope_deg=5.0, front_gate_speed=1.5)
    assert (taller.info.height, taller.info.slope_deg, taller.params.to_dict()["beta"]) == (0.06, 5.0, 0.2)
    assert taller.config.walls[-1].velocity == (0.0, 1.5)
    # the aspect-ratio family: its variants take a and L0, and record their aspect ratio
    column = build_scene("aspect-ratio", aspect=2.0, dx=0.01)
    coarse = column.at_dx(0.0125)
    assert (coarse.info.aspect, coarse.info.height, coarse.config.grid.dx) == (2.0, 0.1, 0.0125)
    wider = column.variant(a=3.0)
    assert (wider.info.aspect, wider.info.height, wider.config.t_end) == (3.0, 3.0 * 0.05, column.config.t_end)
    _same_scene(scenes.aspect_ratio_collapse(2.0, dx=0.01).variant(a=3.0), wider)
    with pytest.raises(ValueError, match="give a, the aspect ratio, or L0 instead of height"):
        column.variant(height=0.2)
    assert build_scene("slope-collapse", sampling="lattice", dx=0.04).sampler is None


def test_the_module_constants_are_the_files():
    from jaxmpm.scenes.collapse import S4_SIDE  # the module's, not the package's (calibration imports it)

    s2, s3, s4 = (shipped_experiment(n) for n in ("gates-collapse", "slope-collapse", "cohesive-collapse"))
    s5, s7 = shipped_experiment("aspect-ratio"), shipped_experiment("aluminium-bars")
    assert (scenes.S2_LENGTH, scenes.S2_HEIGHT, scenes.S3_LENGTH, scenes.S3_HEIGHT) == (
        s2.length, s2.height, s3.length, s3.height)
    assert (scenes.S4_SIDE, scenes.S5_LENGTH, scenes.S7_LENGTH, scenes.S7_HEIGHT) == (
        s4.length, s5.length, s7.length, s7.height)
    assert S4_SIDE == scenes.S4_SIDE == s4.height
    assert scenes.S7_PARAMS == dict(s7.material)
    with pytest.raises(AttributeError):
        scenes.S2_PARAMS  # noqa: B018 (the other materials are their files' [material])


def test_frames_end_on_t_end():
    """t_end (k + 1) / frames rounds above t_end for some frame counts (S2's 100 frames among them)."""
    scene = scenes.gates_collapse(dx=0.02, frames=100)
    assert len(scene.config.frame_times) == 100 and scene.config.frame_times[-1] == scene.config.t_end


def test_an_experiment_made_at_an_aspect_ratio_keeps_its_height():
    member = named_experiment("aspect-ratio", aspect=2.0)
    with pytest.raises(ValueError, match="must be aspect x length"):
        member.replace(height=0.2)
    assert member.replace(height=0.2, aspect=None).scene().info.aspect is None
