"""A cheap objective for the cluster tests: residuals theta - target, a callback that takes a
given time per chunk and leaves a marker file naming the worker's pid (so a test can kill the
worker while it computes), an exception for a < 0 and an engine-like status bit for b > 10."""

import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

TARGET = np.array([0.3, 0.6])


class ToyObjective:
    keys = ("a", "b")

    def __init__(self, marker_dir: str, delay: float):
        self.marker_dir, self.delay = marker_dir, delay

    def _wait(self, theta):
        theta = np.asarray(theta)
        if np.any(theta[..., 0] < 0):
            raise RuntimeError("toy: a < 0 always fails")
        pathlib.Path(self.marker_dir, f"started-{os.getpid()}-{time.time_ns()}").touch()
        time.sleep(self.delay)
        return np.zeros(theta.shape[:-1], np.int32)

    @property
    def dtype(self):
        return jnp.zeros(()).dtype  # JAX's default float: float64 where the worker runs x64

    def check_thetas(self, thetas, name="thetas"):
        """Every row is a parameter set of the toy (a < 0 fails when it runs)."""

    def fingerprint(self):
        return None  # nothing cached: every sweep of the toy compiles its own call

    def describe(self):
        return {"toy": "theta - target", "delay": self.delay}

    def residual_fn(self, theta):
        shape = jax.ShapeDtypeStruct((), jnp.int32)
        zero = jax.pure_callback(self._wait, shape, theta, vmap_method="expand_dims")
        status = jnp.where(theta[1] > 10, jnp.int32(1), jnp.int32(0)) + zero
        r = (theta - jnp.asarray(TARGET, theta.dtype)) * jnp.asarray([1.0, 2.0], theta.dtype)
        return r, {"status": status, "double": 2 * theta}


def make_toy(marker_dir: str, delay: float) -> ToyObjective:
    return ToyObjective(marker_dir, delay)
