"""The command line ``python -m calibration``: flags parsed into the library's option objects, one
library call per command, its JSON printed."""

from .commands import main
from .parser import build_parser

__all__ = ["build_parser", "main"]
