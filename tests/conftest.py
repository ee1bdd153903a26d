"""Shared pytest fixtures and markers for subslope.

- ``gpu`` tests are skipped unless CUDA is available.
- ``reference`` tests are skipped unless lenstronomy is importable.
- Matplotlib is forced onto the Agg backend.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest
import torch

matplotlib.use("Agg")

REPO_ROOT = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")
#: The tiny campaign's config on the snakemake command line.
TINY = ("--configfile", "config/tiny.yaml")


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


def workflow_copy(root: Path) -> Path:
    """A copy of Snakefile, workflow/, config/ and profiles/ in ``root``, as a user has them."""
    shutil.copy(REPO_ROOT / "Snakefile", root)
    shutil.copytree(
        REPO_ROOT / "workflow", root / "workflow", ignore=shutil.ignore_patterns("__pycache__")
    )
    shutil.copytree(REPO_ROOT / "config", root / "config")
    shutil.copytree(REPO_ROOT / "profiles", root / "profiles")
    return root


def run_snakemake(
    workdir: Path, *args: str, mirror: Path | None = None, timeout: int = 300
) -> subprocess.CompletedProcess:
    """``snakemake *args`` in ``workdir`` (data from ``mirror``), output captured."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if mirror is not None:
        env["SUBSLOPE_DATA_MIRROR"] = str(mirror)
    return subprocess.run(
        [str(SNAKEMAKE), *args],
        cwd=workdir,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.fixture(scope="session")
def workdir(tmp_path_factory) -> Path:
    """A workflow folder (:func:`workflow_copy`) shared by the workflow tests."""
    if not SNAKEMAKE.exists():
        pytest.skip(f"snakemake not found next to {sys.executable}")
    return workflow_copy(tmp_path_factory.mktemp("workflow"))


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """`snakemake --cores 2 --configfile config/tiny.yaml`: the whole DAG, once per session,
    in a workflow folder of its own (the dry-run tests keep theirs untouched)."""
    if not SNAKEMAKE.exists():
        pytest.skip(f"snakemake not found next to {sys.executable}")
    data_dir = shared_data_dir()
    if not data_dir.is_dir():
        pytest.skip(f"real data folder not found: {data_dir}")
    root = workflow_copy(tmp_path_factory.mktemp("tiny_campaign"))
    proc = run_snakemake(root, "--cores", "2", *TINY, mirror=data_dir, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return root / "results"
