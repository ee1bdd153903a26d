"""Shared pytest fixtures and markers for subslope.

- ``gpu`` tests are skipped unless CUDA is available.
- ``reference`` tests are skipped unless lenstronomy is importable.
- Matplotlib is forced onto the Agg backend.
- The suite runs on pytest-xdist workers (``-n`` in pyproject.toml, ``--dist loadgroup``).
  The tiny campaign runs once per session for all workers (:func:`tiny_run`). The tests
  of the systematics variants, which run on it, join the xdist group ``systematics``,
  and those that compile the render kernels the group ``compiled``
  (:data:`COMPILED_MODULES`): each group runs on one worker (the variants once, each
  kernel compiled once), the two groups first, then the other tests that read the
  campaign (:data:`CAMPAIGN_FIXTURES`), then the rest.
"""

from __future__ import annotations

import importlib.util
import json
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

if "PYTEST_XDIST_WORKER_COUNT" in os.environ:  # the workers share the cores
    torch.set_num_threads(
        max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    )

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


#: Fixtures that stand for the finished tiny campaign (this file, tests/test_*.py).
CAMPAIGN_FIXTURES = frozenset(
    {"tiny_run", "campaign", "finished_campaign", "systematics_run", "cache_campaign"}
)
#: Modules whose tests torch.compile the population kernels (the render defaults on CPU).
COMPILED_MODULES = frozenset(
    {"test_accuracy_budget", "test_render", "test_fast_paths", "test_pair_kernels"}
)


def _schedule(item) -> tuple[int, str | None]:
    """(rank in the run order, xdist group) of a test."""
    fixtures = set(getattr(item, "fixturenames", ()))
    if "systematics_run" in fixtures:
        return 0, "systematics"
    if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in COMPILED_MODULES:
        return 1, "compiled"
    return (2 if CAMPAIGN_FIXTURES & fixtures else 3), None


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    schedule = {item: _schedule(item) for item in items}
    for item, (_, group) in schedule.items():
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    items.sort(key=lambda item: schedule[item][0])  # stable: module order within a rank
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


def session_folder(tmp_path_factory) -> Path:
    """The temporary folder of the whole test session: shared by the xdist workers (each
    has a base folder of its own inside it), the base folder without xdist."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if "PYTEST_XDIST_WORKER" in os.environ else base


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """`snakemake --cores 2 --configfile config/tiny.yaml`: the whole DAG, once per test
    session whichever xdist worker asks first (the others wait for it and read the same
    folder), in a workflow folder of its own (the dry-run tests keep theirs untouched).
    Tests that change the campaign work on a copy of it."""
    from filelock import FileLock

    if not SNAKEMAKE.exists():
        pytest.skip(f"snakemake not found next to {sys.executable}")
    data_dir = shared_data_dir()
    if not data_dir.is_dir():
        pytest.skip(f"real data folder not found: {data_dir}")
    shared = session_folder(tmp_path_factory)
    root, record = shared / "tiny_campaign", shared / "tiny_campaign.json"
    with FileLock(str(shared / "tiny_campaign.lock")):
        if not record.exists():
            root.mkdir()
            proc = run_snakemake(
                workflow_copy(root), "--cores", "2", *TINY, mirror=data_dir, timeout=1800
            )
            outcome = {"returncode": proc.returncode, "output": proc.stdout + proc.stderr}
            record.write_text(json.dumps(outcome))
    outcome = json.loads(record.read_text())
    assert outcome["returncode"] == 0, outcome["output"]
    return root / "results"
