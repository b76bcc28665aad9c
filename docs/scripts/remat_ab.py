"""The transfers plain or under ``jax.checkpoint`` (``jaxmpm.transfer``, "Reverse mode"), paired
in one process: S4 (β = 0.25, pc0 = 500 Pa, ξ = 50, 0.2 s without the rest stop) at a grid
spacing, its forward run, the forward-mode Jacobian of five keys and the reverse gradient of
the same loss, each compiled under both designs and timed alternately.

    taskset -c 0 python docs/scripts/remat_ab.py [DX]      -> one JSON line (DX default L/8)

It swaps the module's private checkpointed bodies for the plain ones (``_p2g_remat``,
``_g2p_remat``): an A/B of an internal design, not an option of the engine.
"""

import json
import statistics
import sys
import time

import jax
import jax.numpy as jnp

import jaxmpm as jm
from jaxmpm import transfer

KEYS = ("beta", "mu1", "mu2", "I0", "xi")
DESIGNS = {"plain": (transfer._p2g, transfer._g2p_planes), "checkpointed": (transfer._p2g_remat, transfer._g2p_remat)}


def compiled(scene, theta):
    """(kind, design) -> a compiled function of theta, each traced under its design."""
    out = {}
    for design, (p2g_body, g2p_body) in DESIGNS.items():
        transfer._p2g_remat, transfer._g2p_remat = p2g_body, g2p_body
        rollout = jm.make_rollout(scene.config, observer=None)

        def loss(theta, rollout=rollout):
            final, _ = rollout(scene.state, scene.params.replace(**dict(zip(KEYS, theta))))
            return jnp.max(final.x[:, 0]) + jnp.mean(final.x[:, 1])

        for kind, fn in (("forward", jax.jit(loss)), ("jacfwd", jax.jit(jax.jacfwd(loss))),
                         ("grad", jax.jit(jax.grad(loss)))):
            jax.block_until_ready(fn(theta))
            out[kind, design] = fn
    transfer._p2g_remat, transfer._g2p_remat = DESIGNS["checkpointed"]
    return out


def main():
    dx = float(sys.argv[1]) if len(sys.argv) > 1 else 0.089 / 8
    scene = jm.scenes.cohesive_collapse(beta=0.25, dx=dx, pc0=500.0, xi=50.0, t_end=0.2, rest=False)
    theta = jnp.asarray([float(getattr(scene.params, k)) for k in KEYS], scene.state.x.dtype)
    fns = compiled(scene, theta)
    times = {k: [] for k in fns}
    for _ in range(7):
        for k, fn in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(fn(theta))
            times[k].append(time.perf_counter() - start)
    med = {f"{kind}_{design}_s": round(statistics.median(v), 4) for (kind, design), v in times.items()}
    ratio = {kind: round(med[f"{kind}_checkpointed_s"] / med[f"{kind}_plain_s"], 3)
             for kind in ("forward", "jacfwd", "grad")}
    print(json.dumps({"dx": dx, "n_particles": scene.state.n_particles, **med, "checkpointed_over_plain": ratio,
                      "grad_over_forward": {d: round(med[f"grad_{d}_s"] / med[f"forward_{d}_s"], 2) for d in DESIGNS}}))


if __name__ == "__main__":
    main()
