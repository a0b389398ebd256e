"""Suite-wide settings."""
from __future__ import annotations

import os
import sys

import pytest
from hypothesis import settings

# The property tests draw the same examples on every run (``derandomize``; numpy, numba and hypothesis are pinned in
# constraints.txt), so that the suite passes or fails the same way each time. ``HYPOTHESIS_PROFILE=search`` draws new
# ones (with ``--hypothesis-seed=N``, the same again): a search for counterexamples, not a CI run. What such
# searches found is a test of its own (tests/test_separation.py: the QP measured from a wish it was never asked
# for; tests/test_fence_geometry.py: the EQUAL docstring).
settings.register_profile("deterministic", derandomize=True)
settings.register_profile("search", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))


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
