"""Shared pytest fixtures and markers for subslope.

- ``gpu`` tests are skipped unless CUDA is available.
- ``reference`` tests are skipped unless lenstronomy is importable.
- Matplotlib is forced onto the Agg backend.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import matplotlib
import numpy as np
import pytest
import torch

matplotlib.use("Agg")

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """Folder with the real data (``SUBSLOPE_DATA_MIRROR`` or ``../shared/data``)."""
    env = os.environ.get("SUBSLOPE_DATA_MIRROR")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "data")


@pytest.fixture
def one_thread():
    """Run the test on one torch thread (timing-independent numerics, fair to the machine)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def pytest_collection_modifyitems(config, items):
    has_cuda = torch.cuda.is_available()
    has_lenstronomy = importlib.util.find_spec("lenstronomy") is not None
    skip_gpu = pytest.mark.skip(reason="needs a CUDA device")
    skip_ref = pytest.mark.skip(reason="lenstronomy not installed (pip install -e '.[reference]')")
    for item in items:
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(skip_gpu)
        if "reference" in item.keywords and not has_lenstronomy:
            item.add_marker(skip_ref)


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded numpy generator (seed 20230817)."""
    return np.random.default_rng(20230817)


@pytest.fixture
def data_dir() -> Path:
    path = shared_data_dir()
    if not path.is_dir():
        pytest.skip(f"real data folder not found: {path}")
    return path


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


def devices() -> list[str]:
    """CPU always; CUDA when present (for parametrising device tests)."""
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
