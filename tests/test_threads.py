"""XLA's CPU threads chosen before JAX starts (``jaxmpm.threads``): the flags reach XLA_FLAGS
with the user's own kept, a choice made too late is an error, not silently ignored."""

import os
import subprocess
import sys

import pytest

from jaxmpm.threads import SINGLE_THREAD_FLAGS


def _python(code: str, xla_flags: str | None) -> subprocess.CompletedProcess:
    """``code`` in a fresh Python allowed every core (the suite's own process is pinned to one)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    code = f"import os; os.sched_setaffinity(0, range(os.cpu_count())); {code}"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)


several_cores = pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or (os.cpu_count() or 1) < 2,
                                   reason="pinning to one core needs an affinity call and two cores")
REPORT = ("import jax.numpy as jnp; jnp.zeros(1).block_until_ready(); from jaxmpm.threads import allowed_cores; "
          "print(len(os.sched_getaffinity(0)), len(allowed_cores()) == os.cpu_count(), "
          "os.environ.get('XLA_FLAGS', 'unset'))")


@several_cores
def test_one_core_before_the_backend_starts_keeps_the_users_flags_and_the_allowed_cores():
    """The default pins the process to one core (the XLA flags alone no longer limit JAX's pools)
    and adds the flags to a user's own; ``allowed_cores`` still names every core, for the worker
    processes; --threads all changes nothing."""
    code = f"from jaxmpm.threads import apply_threads; apply_threads(None); {REPORT}"
    default = _python(code, None)
    assert default.returncode == 0, default.stderr
    assert default.stdout.strip().split(maxsplit=2) == ["1", "True", SINGLE_THREAD_FLAGS]
    own = _python(code.replace("apply_threads(None)", "apply_threads('1')"), "--xla_cpu_enable_fast_math=false")
    flags = f"--xla_cpu_enable_fast_math=false {SINGLE_THREAD_FLAGS}"
    assert own.stdout.strip().split(maxsplit=2) == ["1", "True", flags]
    every = _python(code.replace("apply_threads(None)", "apply_threads('all')"), None)
    assert every.stdout.split() == [str(os.cpu_count()), "True", "unset"]


@several_cores
def test_a_choice_after_the_backend_started_is_an_error():
    late = _python("import jax.numpy as jnp; jnp.zeros(1).block_until_ready(); "
                   "from jaxmpm.threads import use_one_thread; use_one_thread()", None)
    assert late.returncode != 0 and "before the first computation" in late.stderr


def test_bad_choice_names_the_option():
    from jaxmpm.threads import apply_threads

    with pytest.raises(ValueError, match="--threads"):
        apply_threads("2")


def test_the_backend_check_is_made_through_public_jax():
    """Whether the backend has started is asked through JAX's public configuration (no private
    ``jax._src``), before and after the first computation, and the question changes nothing."""
    import ast
    import pathlib

    tree = ast.parse((pathlib.Path(__file__).resolve().parents[1] / "jaxmpm" / "threads.py").read_text())
    imported = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    imported += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert "jax" in imported and not [m for m in imported if "_src" in m]
    code = ("import jax; from jaxmpm.threads import _backend_started; before = jax.config.jax_num_cpu_devices; "
            "print(_backend_started(), jax.config.jax_num_cpu_devices == before); "
            "import jax.numpy as jnp; jnp.zeros(1).block_until_ready(); "
            "print(_backend_started(), jax.config.jax_num_cpu_devices == before, len(jax.devices('cpu')))")
    run = _python(code, None)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "True", "True", "True", "1"]
