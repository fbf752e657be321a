import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))  # helpers.py


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    """~250 lattice particles falling and spreading, 5 + 1 views, 8 frames, 64x64 (own renderer)."""
    from gf_core.synthetic import falling_blob, splat_dataset

    return splat_dataset(tmp_path_factory.mktemp("blob"), falling_blob(n_side=9, frames=8))


@pytest.fixture(scope="module")
def small_blob(tmp_path_factory):
    """The same at 7^3 particles and 6 frames."""
    from gf_core.synthetic import falling_blob, splat_dataset

    return splat_dataset(tmp_path_factory.mktemp("small_blob"), falling_blob(n_side=7, frames=6))
