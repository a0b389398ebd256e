"""Suite-wide settings."""
from __future__ import annotations

import sys

import pytest


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tests that train or update a learner run with one torch thread, as the trainer does (``train.threads``):
    with torch's default of one thread per core, two threads on 2 busy cores wait for each other and a test of
    200 small updates took 64 s instead of 3. Tests that import no torch are left alone (torch is not imported
    here: runtime and groundstation tests must not need it)."""
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
