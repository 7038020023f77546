import os

import pytest

# Keep Warp quiet and on the CPU in tests; CUDA tests opt in explicitly.
os.environ.setdefault("WARP_QUIET", "1")


@pytest.fixture(scope="session")
def cuda_available():
    import warp as wp

    from abmpm.simulation import init_warp

    init_warp()
    return wp.get_cuda_device_count() > 0
