"""Shared fixtures. Real data lives beside the repository in ../shared/data and is never copied in."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# A kernel that fails its first-use self-check would otherwise be swapped for the dense path with a warning, and
# every test comparing "the kernel" with the reference would pass on the dense path.  Strict makes it an error.
# (Tests of the fallback itself set the variable with monkeypatch; subprocesses of the CLI tests inherit it.)
os.environ.setdefault("MODI_EXT_SELFCHECK", "strict")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MODI_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to ../shared/data; skips the test with a reason when it is absent."""
    if not (SHARED_DATA / "bvh").is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (set MODI_SHARED_DATA or place ../shared beside the repo)")
    return SHARED_DATA


@pytest.fixture
def one_torch_thread():
    """One intra-op thread for tests of tiny models and tensors: OpenMP hand-offs cost more than the work there, and
    spinning workers make it far worse on a shared 2-core CI machine. Modules opt in with
    ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "cuda: needs a CUDA GPU and the CUDA kernels (skipped otherwise)")
    config.addinivalue_line("markers", "cuda_emulated: the CUDA kernels run on the CPU emulator (modi_ext._C_emu)")
