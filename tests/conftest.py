import numpy as np
import pytest

from lapreco_hil.warp_device import init_warp


@pytest.fixture(scope="session")
def warp_cpu():
    """Warp initialised quietly; tests run its kernels on the CPU device (CI has no GPU)."""
    init_warp()
    return "cpu"


@pytest.fixture
def sm90_ptx(warp_cpu, tmp_path):
    """``ptx(module) -> str``: the PTX Warp's bundled NVRTC makes of a kernel module for an H100 (sm_90). CI has
    no GPU: CUDA code generation errors (types the CPU build tolerates) show here rather than on the GPU
    machine. Skips where the Warp build has no NVRTC."""
    import warp as wp
    from pathlib import Path

    def ptx(module) -> str:
        try:
            outputs = wp.compile_aot_module(module, arch=90, module_dir=tmp_path, use_ptx=True)
        except RuntimeError as exc:
            if "nvrtc" in str(exc).lower():
                pytest.skip(f"no CUDA compiler in this Warp build: {exc}")
            raise
        return Path(outputs[0]).read_text()

    return ptx


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def skull_world(warp_cpu):
    """The simulated skull world at 320x240 on the CPU device, built once (its mesh, renderer and robot).
    Tests read it (render at a given time, the true surface); none advances or changes it."""
    from lapreco_hil.simulators.world import SimSettings, SimWorld

    return SimWorld(SimSettings(scene="skull", width=320, height=240, device=warp_cpu))


@pytest.fixture(scope="session")
def small_skull_session(tmp_path_factory, warp_cpu):
    """A 12-frame 256x192 simulated skull session with ground truth, recorded once (`lapreco sim-record`'s
    work) for the tests that only need some recorded input to replay. Read-only: copy it to change it."""
    from lapreco_hil.app.record import sim_record

    path = tmp_path_factory.mktemp("sessions") / "skull-12"
    sim_record("skull", str(path), frames=12, resolution=(256, 192), device=warp_cpu, progress=False)
    return path
