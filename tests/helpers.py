"""What several test files need: the command lines run as a user runs them (a subprocess) or
through their ``main()`` (in process, the exit code and the error), and JSON read strictly."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def cli(module: str, *args: str, cwd=None, env=None, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS...`` in a subprocess: its return code, stdout and stderr (text)."""
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout)


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
