"""Writes tests/data/s4_release_0_2_0.npz, the reference of tests/test_step_design.py, with the
jaxmpm found first on the path (release 0.2.0 for the shipped file):

    PYTHONPATH=/path/to/jaxmpm-0.2.0 python tests/data/make_release_reference.py tests/data/s4_release_0_2_0.npz

S4 at dx = L/6, p_c0 = 500 Pa, ξ = 50, β = 0.25, float64, to t = 0.05 s: the final positions and
their forward-mode derivatives with respect to β and μ1.
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np


def main(path):
    jax.config.update("jax_enable_x64", True)
    import jaxmpm as jm
    from jaxmpm.scenes import cohesive_collapse

    kw = dict(beta=0.25, dx=0.089 / 6, pc0=500.0, xi=50.0, dtype="float64", t_end=0.05)
    try:
        scene = cohesive_collapse(rest=False, **kw)
    except (TypeError, ValueError):  # release 0.2.0 has no rest stop (it takes rest= for a parameter)
        scene = cohesive_collapse(**kw)
    rollout = jm.make_rollout(scene.config, observer=None)

    def run(theta):
        final, _ = rollout(scene.state, scene.params.replace(beta=theta[0], mu1=theta[1]))
        return final.x

    theta = jnp.asarray([0.25, float(scene.params.mu1)])
    tangents = {key: jax.jit(lambda t, d=d: jax.jvp(run, (t,), (jnp.asarray(d),))[1])(theta)
                for key, d in (("dx_dbeta", [1.0, 0.0]), ("dx_dmu1", [0.0, 1.0]))}
    np.savez_compressed(path, x=np.asarray(jax.jit(run)(theta)), theta=np.asarray(theta), jaxmpm=jm.__file__,
                        **{k: np.asarray(v) for k, v in tangents.items()})


if __name__ == "__main__":
    main(sys.argv[1])
