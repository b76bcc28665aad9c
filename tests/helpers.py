"""What several test files need: the command lines run as a user runs them (a subprocess) or
through their ``main()`` (in process, the exit code and the error), JSON read strictly, and the
tiny S4 problem the calibration tests fit (its scene, the model's own data, its flags)."""

from __future__ import annotations

import contextlib
import io
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from jaxmpm.scenes import S4_SIDE

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: The shipped synthetic S4 profile (β = 0.25, t = 0.5 s) that the command-line fits read.
S4_DATA = ROOT / "experiments_data" / "synthetic" / "S4_beta0.25.csv"
#: The tiny S4 scene's cell: a sixth of the column's side, 144 particles.
TINY_DX = S4_SIDE / 6
#: The command lines' flags for the tiny scene, quiet and printing JSON.
TINY_FLAGS = ("--dx", str(TINY_DX), "--no-progress", "--json")


def cli(module: str, *args: str, cwd=None, env=None, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS...`` in a subprocess: its return code, stdout and stderr (text)."""
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout)


def call_main(main, argv) -> tuple[int, str, str]:
    """``main(argv)`` (a command line's entry point) in this process with its output captured:
    (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def main_exit(module: str, argv, capsys) -> tuple[int, str]:
    """``MODULE.__main__.main(argv)`` in this process, expected to exit (an error, status 2):
    the exit code and what it printed on stderr."""
    main = __import__(f"{module}.__main__", fromlist=["main"]).main
    with pytest.raises(SystemExit) as exit_:
        main(list(map(str, argv)))
    return exit_.value.code, capsys.readouterr().err


def strict_json(text: str):
    """json.loads that refuses NaN and Infinity (which json.loads accepts by default): the
    command lines promise valid JSON."""
    def refuse(name):
        raise ValueError(f"invalid JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def tiny_s4(beta: float = 0.25, dx: float = TINY_DX, t_end: float = 0.1, **values):
    """The tiny cohesive collapse (S4 at dx = L/6: 144 particles; a 0.1 s run takes well under
    a second); ``values`` go to ``jaxmpm.scenes.cohesive_collapse``."""
    from jaxmpm import scenes

    return scenes.cohesive_collapse(beta, dx=dx, t_end=t_end, **values)


def placeholder_objective(scene, keys, xs=None, times=None):
    """An ``Objective`` that observes the final profile at ``xs`` and the front at ``times``
    (either may be None) against placeholder data (ones), so that its prediction at some θ can
    be made into data."""
    from calibration import FrontTarget, Objective, ProfileTarget

    profile = None if xs is None else ProfileTarget(np.asarray(xs), np.ones(len(xs)))
    front = None if times is None else FrontTarget(np.asarray(times), np.ones(len(times)))
    return Objective(scene, keys, profile=profile, front=front, check_data=False)


def model_data(scene, keys, theta, xs=None, times=None):
    """Data the model itself makes at ``theta``: the final profile at ``xs`` and the front at
    ``times`` as ``(ProfileTarget or None, FrontTarget or None)``, from one run that must
    succeed (status 0)."""
    from calibration import FrontTarget, ProfileTarget

    _, pred = placeholder_objective(scene, keys, xs, times).residuals(np.asarray(theta))
    assert int(pred["status"]) == 0
    profile = None if xs is None else ProfileTarget(np.asarray(xs), np.asarray(pred["h"]))
    front = None if times is None else FrontTarget(np.asarray(times), np.asarray(pred["front"]))
    return profile, front
