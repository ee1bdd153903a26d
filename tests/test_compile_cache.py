"""The on-disk compile cache: where it lives, and that kernels loaded from it without
tracing give the same numbers as the process that compiled them."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import torch

from subslope.render import kernels
from subslope.render.kernels import kernel_source_key, use_compile_cache

# One process: evaluate the compiled kernels named in argv[2] (comma-separated: far = the
# far-field EPL kernel, few = the few-member NFW kernel, direct = the direct EPL sum) on a
# fixed input; print the sums, how many graphs came from the dynamo cache and which
# kernels fell back to eager.
_JOB = """
import json, sys, torch
from torch._dynamo.utils import counters  # fills in torch's default folder
from subslope.physics.pairs.sums import member_table
from subslope.render import kernels
from subslope.render.kernels import kernels_for, use_compile_cache
use_compile_cache(sys.argv[1])
from subslope.render.settings import RenderSettings
torch.set_num_threads(1)
g = torch.Generator().manual_seed(0)
def u(lo, hi, n):
    return lo + (hi - lo) * torch.rand(1, n, generator=g)
epl = member_table("epl", dict(gamma=u(1.2, 2.8, 40), amp=u(1e-4, 1e-3, 40), e1=u(-.2, .2, 40),
                               e2=u(-.2, .2, 40), x=u(-2, 2, 40), y=u(-2, 2, 40)), 8)
nfw = member_table("nfw", dict(r_s=u(.05, .3, 3), alpha_rs=u(1e-3, 1e-2, 3), x=u(-2, 2, 3),
                               y=u(-2, 2, 3)), 0)
x, y, inv_rc2 = u(-2, 2, 500), u(-2, 2, 500), 1.0 / u(0.1, 0.5, 40) ** 2
k = kernels_for(RenderSettings(compile="on"), torch.device("cpu"))
calls = {"far": lambda: k.far(x, y, epl, "epl", inv_rc2), "few": lambda: k.few(x, y, nfw, "nfw"),
         "direct": lambda: k.direct(x, y, epl, "epl")}
out = [float(t.double().sum()) for name in sys.argv[2].split(",") for t in calls[name]()]
print(json.dumps({"sums": out, "hits": counters["dynamo_cache"]["dynamo_cache_hit"],
                  "eager": sorted(map(str, kernels._COMPILE_FAILED))}))
"""


def _run(folder, *extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.endswith("_CACHE_DIR")}
    env["OMP_NUM_THREADS"] = "1"
    command = [sys.executable, "-c", _JOB, str(folder), *extra]
    proc = subprocess.run(command, capture_output=True, text=True, env=env, check=True)
    return {**json.loads(proc.stdout.strip().splitlines()[-1]), "stderr": proc.stderr}


def test_the_compile_cache_is_set_once_and_the_environment_wins(tmp_path, monkeypatch):
    for name in ("TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR"):
        monkeypatch.delenv(name, raising=False)
    kept = []
    monkeypatch.setattr(kernels, "keep_traced_graphs", lambda: kept.append(True))
    env = use_compile_cache(tmp_path / "cc")
    assert env == {
        "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cc" / kernel_source_key()),
        "TRITON_CACHE_DIR": str(tmp_path / "cc" / "triton"),
    }
    assert (tmp_path / "cc" / kernel_source_key()).is_dir()
    assert kept == [True]
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", "/mine")
    monkeypatch.delenv("TRITON_CACHE_DIR")
    assert use_compile_cache(tmp_path / "other")["TORCHINDUCTOR_CACHE_DIR"] == "/mine"
    assert use_compile_cache(None)["TORCHINDUCTOR_CACHE_DIR"] == "/mine"
    assert kept == [True], "a folder the user chose gets no traced graphs of ours"


def test_torch_own_default_folder_does_not_count_as_chosen(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", kernels.torch_default_folder())
    monkeypatch.delenv("TRITON_CACHE_DIR", raising=False)
    monkeypatch.setattr(kernels, "keep_traced_graphs", lambda: None)
    env = use_compile_cache(tmp_path / "cc")
    assert env["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "cc" / kernel_source_key())


def test_the_key_follows_the_kernel_sources_and_torch(monkeypatch):
    key = kernel_source_key()
    assert len(key) == 12 and int(key, 16) >= 0
    monkeypatch.setattr(torch, "__version__", torch.__version__ + "+other")
    assert kernel_source_key() != key


def test_kernels_loaded_without_tracing_give_the_same_numbers(tmp_path):
    first = _run(tmp_path / "cc", "far,few")
    second = _run(tmp_path / "cc", "far,few")
    assert first["hits"] == 0
    assert second["hits"] >= 2, "the second process traced the kernels again"
    assert second["sums"] == first["sums"]
    assert all(map(math.isfinite, first["sums"]))
    assert first["eager"] == second["eager"] == []


def test_tracing_with_kept_graphs_prints_no_guard_notices(tmp_path):
    """torch warns once per guard it leaves out of a kept graph (hundreds per job): the
    filter of :func:`subslope.render.kernels.keep_traced_graphs` drops exactly those."""
    import logging

    from subslope.render.kernels import PRECOMPILE_GUARD_NOTICE, drop_precompile_guard_notices

    traced = _run(tmp_path / "cc", "far,few")
    assert "guard on" not in traced["stderr"], traced["stderr"][-2000:]
    assert traced["eager"] == []

    def record(msg):
        return logging.LogRecord("torch._dynamo.guards", logging.WARNING, "", 0, msg, (), None)

    assert not drop_precompile_guard_notices(record("%s " + PRECOMPILE_GUARD_NOTICE))
    assert drop_precompile_guard_notices(record("a real warning"))


def test_graphs_of_several_processes_and_new_ones_live_side_by_side(tmp_path):
    # each process numbers the globals its graphs install from 0 unless told otherwise:
    # graphs saved by two processes, and a graph traced beside them, must not collide
    _run(tmp_path / "cc", "far")
    _run(tmp_path / "cc", "few")
    mixed = _run(tmp_path / "cc", "far,few,direct")
    assert mixed["hits"] >= 2
    assert mixed["eager"] == [], "a kernel fell back to eager"
    assert _run(tmp_path / "cc", "far,few,direct")["sums"] == mixed["sums"]
