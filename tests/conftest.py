"""Tests run in float64 with strict dtype promotion, set here and never at import time.

The suite runs in pytest-xdist workers (``-n auto --dist loadfile`` in pyproject.toml: a file's
tests, and its module fixtures, stay in one worker), worker k pinned to the k-th core
(``jaxmpm.threads.use_one_thread``), as the command lines run: the test problems are small, and on
two cores one single-core process per core does more work than processes whose XLA pools each
spread over both (a whole S4 run at dx = 4 mm: 5.8 s on one core, 13.6 s on XLA's pool).
JAXMPM_TEST_THREADS=all leaves XLA its own choice."""

import os

import jax

from jaxmpm.threads import use_one_thread  # starts no JAX backend

# The command lines' default --workers is every core; the suite already keeps both busy, so its
# command-line runs stay in one process (tests/test_workers.py covers the worker processes).
os.environ.setdefault("JAXMPM_WORKERS", "1")

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# Compiling, not running, is most of what the small test problems cost (tests/test_sweep.py: 46 s
# cold, 15 s with its programs compiled), and the files compile many of the same programs in
# different workers. XLA's persistent cache keeps each compiled program once, keyed by the program,
# the jax/jaxlib versions and the compile options, so the workers, the slow run after the default one
# and the command lines' subprocesses share them. It caches executables, never results. The cache
# lives in the clone (gitignored), so a fresh clone starts cold; JAXMPM_TEST_XLA_CACHE=off disables
# it, any other value names another folder.
_XLA_CACHE = os.environ.get("JAXMPM_TEST_XLA_CACHE") or os.path.join(
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".xla_cache"
)
if _XLA_CACHE != "off":
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _XLA_CACHE)  # the command lines' subprocesses
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def pytest_configure(config):
    # In the workers only: xdist's controller runs no test, and the workers it starts would
    # inherit its one core.
    if os.environ.get("JAXMPM_TEST_THREADS") == "all":
        return
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker:
        use_one_thread(int(worker.removeprefix("gw")))
    elif not getattr(config.option, "numprocesses", None):
        use_one_thread()

