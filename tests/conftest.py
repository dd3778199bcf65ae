import numpy as np
import pytest

from lapreco_hil.warp_device import init_warp


@pytest.fixture(scope="session")
def warp_cpu():
    """Warp initialised quietly; tests run its kernels on the CPU device (CI has no GPU)."""
    init_warp()
    return "cpu"


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
