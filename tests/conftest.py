"""Test-session settings: one torch thread (6-10x faster for small step-by-step work on 2 cores)."""

import os
import tempfile

import numpy as np
import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ["RAT_ZOO"] = tempfile.mkdtemp(prefix="rat-test-zoo-")  # no test writes to, or reads from, a user's zoo
torch.set_num_threads(1)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)
