"""Tests run in float64 with strict dtype promotion, set here and never at import time."""

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture(autouse=True)
def _x64():
    yield
