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


# Under pytest-xdist every worker is a process of its own: give each an equal share
# of the cores for the solver's CPU threads (tests that measure threading set theirs).
if "PYTEST_XDIST_WORKER_COUNT" in os.environ and "ABMPM_THREADS" not in os.environ:
    _workers = int(os.environ["PYTEST_XDIST_WORKER_COUNT"])
    os.environ["ABMPM_THREADS"] = str(max(1, (os.cpu_count() or 1) // _workers))
