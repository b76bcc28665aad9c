"""The version of jaxmpm (and of its calibration package): the only place it is written."""

__version__ = "0.2.0"
