import jax
import pytest


@pytest.fixture
def x64():
    """Run a test in float64 (accuracy tests): build bodies and controllers inside it."""
    with jax.enable_x64(True):
        yield
