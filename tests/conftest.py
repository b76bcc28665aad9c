"""Tests run in float64 with strict dtype promotion, set here and never at import time.

The suite runs in pytest-xdist workers (``-n auto --dist loadfile`` in pyproject.toml: a file's
tests, and its module fixtures, stay in one worker), each on a single-threaded XLA unless
XLA_FLAGS says otherwise: the test problems are small, and on two cores one single-threaded
process per core does more work than processes that each spread over both (a 1.1 s Jacobian of
S7 at H/6 takes 1.7 s on XLA's default thread pool)."""

import os

from jaxmpm.threads import SINGLE_THREAD_FLAGS  # starts no JAX backend

os.environ.setdefault("XLA_FLAGS", SINGLE_THREAD_FLAGS)
# The command lines' default --workers is every core; the suite already keeps both busy, so its
# command-line runs stay in one process (tests/test_workers.py covers the worker processes).
os.environ.setdefault("JAXMPM_WORKERS", "1")

import jax  # noqa: E402  (after XLA_FLAGS, which the backend reads when it starts)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

