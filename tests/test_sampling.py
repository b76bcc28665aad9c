"""Particle sampling (jaxmpm.sampling): lattice, jittered lattice, Poisson disk."""

import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.sampling import particles_per_cell
from jaxmpm.scenes import S4_SIDE

BOX = ((0.01, 0.02), (0.09, 0.07))  # 0.08 m × 0.05 m, the S2 column
DX = 0.003


def _inside(x, lower, upper):
    return np.all((x >= np.asarray(lower)) & (x <= np.asarray(upper)))


@pytest.mark.parametrize("sampling", ["lattice", "jitter", "poisson"])
def test_every_sampler_fills_the_box_with_the_body_volume(sampling):
    """All particles lie in the box; V0 = box volume / N, so Σ V0 is the body's volume (1e-12);
    the mean particles per cell is ppc^dim within 2 % (lattice: the spacing is stretched to tile
    the box, 53 × 33 rows for 0.08/0.0015 = 53.3 and 0.05/0.0015 = 33.3; Poisson disk: within
    15 %, its count is random)."""
    lower, upper = BOX
    x, vol = jm.seed_box(lower, upper, DX, 2, sampling=sampling, seed=3)
    assert x.shape[1] == 2 and _inside(x, lower, upper)
    np.testing.assert_allclose(vol.sum(), 0.08 * 0.05, rtol=1e-12)
    assert np.all(vol == vol[0])
    ppc = particles_per_cell(len(x), lower, upper, DX)
    assert abs(ppc / 4.0 - 1.0) < (0.15 if sampling == "poisson" else 0.02), ppc
    if sampling != "poisson":
        assert len(x) == 53 * 33


def test_lattice_is_regular_and_ignores_the_seed():
    lower, upper = BOX
    x, _ = jm.seed_box(lower, upper, DX, 3)
    xs, ys = np.unique(x[:, 0]), np.unique(x[:, 1])
    assert len(xs) == 80 and len(ys) == 50  # 0.08 / 0.001, 0.05 / 0.001
    np.testing.assert_allclose(np.diff(xs), 0.001, rtol=1e-9)
    np.testing.assert_allclose(xs[0] - lower[0], 0.0005, rtol=1e-9)
    x2, _ = jm.seed_box(lower, upper, DX, 3, seed=7)
    np.testing.assert_array_equal(x, x2)
    x3, _ = jm.seed_box((0, 0, 0), (0.03, 0.03, 0.06), 0.01, (2, 2, 3))
    assert len(x3) == 6 * 6 * 18


def test_jitter_keeps_one_particle_per_sub_cell_and_is_reproducible():
    lower, upper = BOX
    base, _ = jm.seed_box(lower, upper, DX, 2)
    x, _ = jm.seed_box(lower, upper, DX, 2, sampling="jitter", seed=11)
    spacing = (np.asarray(upper) - np.asarray(lower)) / np.array([53, 33])
    assert np.all(np.abs(x - base) <= 0.5 * spacing + 1e-15)
    assert np.std(x - base) > 0.2 * spacing.min()  # actually jittered
    np.testing.assert_array_equal(x, jm.seed_box(lower, upper, DX, 2, sampling="jitter", seed=11)[0])
    assert not np.array_equal(x, jm.seed_box(lower, upper, DX, 2, sampling="jitter", seed=12)[0])


@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])  # 3D: 19 s
def test_poisson_disk_keeps_its_radius_and_is_reproducible(dim):
    """No two particles closer than the sampling radius r = dx (0.62 / ppc^2)^(1/2) (2D;
    (0.63 / ppc^3)^(1/3) in 3D); the same seed gives the same sample, another seed another."""
    from scipy.spatial.distance import pdist

    lower, upper = ((0.0,) * dim, (0.04,) * (dim - 1) + (0.03,))
    dx, ppc = 0.006, 2.45  # the reference code's 6 per cell in 2D
    x, vol = jm.seed_box(lower, upper, dx, ppc, sampling="poisson", seed=5)
    radius = dx * ({2: 0.62, 3: 0.63}[dim] / ppc**dim) ** (1.0 / dim)
    assert pdist(x).min() >= radius * (1 - 1e-12)
    assert abs(particles_per_cell(len(x), lower, upper, dx) / ppc**dim - 1.0) < 0.2
    np.testing.assert_array_equal(x, jm.seed_box(lower, upper, dx, ppc, sampling="poisson", seed=5)[0])
    assert not np.array_equal(x, jm.seed_box(lower, upper, dx, ppc, sampling="poisson", seed=6)[0])


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(sampling="random"), "sampling must be one of"),
        (dict(ppc=2.5), "ppc must be a positive integer"),
        (dict(ppc=0), "ppc must be a positive integer"),
        (dict(ppc=0.5, sampling="poisson"), "ppc must be a number >= 1"),
        (dict(seed=-1, sampling="jitter"), "seed must be a non-negative integer"),
        (dict(dx=0.0), "dx must be > 0"),
    ],
)
def test_bad_sampling_input_names_the_argument(kw, match):
    args = dict(lower=BOX[0], upper=BOX[1], dx=DX)
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        jm.seed_box(**args)


def test_scenes_take_the_sampling_options():
    s = jm.scenes.cohesive_collapse(0.25, dx=S4_SIDE / 8, t_end=0.01, ppc=3, sampling="jitter", seed=2)
    assert s.info.sampling == "jitter" and s.info.ppc == 3 and s.info.seed == 2
    np.testing.assert_allclose(np.sum(s.state.vol0), 0.089 * 0.089, rtol=1e-6)
    with pytest.raises(ValueError, match="sampling must be one of"):
        jm.scenes.cohesive_collapse(0.25, dx=S4_SIDE / 8, sampling="grid")
