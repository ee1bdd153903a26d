"""The population kernels of a render call, compiled once per process and device.

:func:`kernels_for` returns the fused pair kernels of :mod:`subslope.physics.pairs`
either ``torch.compile``'d (``RenderSettings.compile`` 'on', or 'auto' on a CPU with a
C compiler) or eager. Compiled graphs are cached per (device type, kernel) for the
life of the process; :func:`clear_cache` forgets them (tests use it to exercise a
fresh compile).
"""

from __future__ import annotations

import atexit
import hashlib
import itertools
import logging
import os
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from subslope.digests import package_digest
from subslope.physics.pairs.sums import (
    circle_peaks,
    direct_sums,
    direct_sums_few,
    far_sums,
    few_sums_with_sheet,
    near_tile_sums,
)
from subslope.render.settings import RenderSettings

__all__ = [
    "FEW_MEMBERS",
    "Kernels",
    "clear_cache",
    "kernel_source_key",
    "keep_traced_graphs",
    "kernels_for",
    "torch_default_folder",
    "use_compile_cache",
]

log = logging.getLogger(__name__)

_COMPILED: dict[Any, Any] = {}
_COMPILE_FAILED: set = set()
_KEEPING = False  # keep_traced_graphs ran in this process
_MAX_KERNEL_GRAPHS = 64
_KERNEL_FUNCTIONS = {
    "direct": direct_sums,
    "few": direct_sums_few,
    "few_sheet": few_sums_with_sheet,
    "far": far_sums,
    "near": near_tile_sums,
    "peaks": circle_peaks,
}
#: Populations of fewer members than this are summed by ``direct_sums_few`` (members
#: on the outer axis) instead of ``direct_sums`` (members vectorised).
FEW_MEMBERS = 32


@dataclass(frozen=True)
class Kernels:
    """The population kernels of one render call (compiled or eager)."""

    direct: Any
    few: Any
    few_sheet: Any
    far: Any
    near: Any
    peaks: Any
    compiled: bool


def use_compile_cache(folder: str | os.PathLike[str] | None) -> dict[str, str]:
    """Point torch.compile's on-disk caches at ``folder`` (made absolute, created):
    ``TORCHINDUCTOR_CACHE_DIR`` (``<folder>/<kernel key>``, :func:`kernel_source_key`) and
    ``TRITON_CACHE_DIR`` (``<folder>/triton``), each only where the environment does not
    set it already (torch's own default, which importing parts of torch fills in, does not
    count as set). Where the inductor folder is ours, dynamo's traced graphs are kept there
    too (:func:`keep_traced_graphs`), so that a later process loads the kernels without
    tracing them. Call before the first compile; returns the variables in effect."""
    if folder is not None:
        root = Path(folder).resolve()
        ours = os.environ.get("TORCHINDUCTOR_CACHE_DIR") in (None, torch_default_folder())
        if ours:
            os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(root / kernel_source_key())
        os.environ.setdefault("TRITON_CACHE_DIR", str(root / "triton"))
        Path(os.environ["TORCHINDUCTOR_CACHE_DIR"]).mkdir(parents=True, exist_ok=True)
        if ours:
            keep_traced_graphs()
    return {
        k: os.environ[k] for k in ("TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR") if k in os.environ
    }


def torch_default_folder() -> str:
    """torch's own inductor folder (``/tmp/torchinductor_<user>``), made absolute."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    return os.path.abspath(default_cache_dir())


def kernel_source_key() -> str:
    """12 hex digits of the SHA-256 of the kernels' sources (this module and
    :mod:`subslope.physics.pairs`, :func:`subslope.digests.package_digest`) and the torch
    version. A traced graph loaded from disk is not traced again, so module-level
    constants that it baked in (the polynomial coefficients) could go stale; a folder per
    key rules that out."""
    code = package_digest(("render/kernels.py", "physics/pairs"))
    return hashlib.sha256(f"{torch.__version__}\0{code}".encode()).hexdigest()[:12]


def keep_traced_graphs() -> None:
    """Keep dynamo's traced graphs in the inductor folder (torch's caching precompile,
    ``torch._dynamo.config.caching_precompile``) and write them when the process ends.
    A fresh process then skips dynamo's symbolic tracing of every kernel graph it
    finds there (about 1 s a graph on one core). Torch calls the feature experimental:
    the graphs of a process whose save fails are traced again by the next one."""
    global _KEEPING
    if _KEEPING:
        return
    _KEEPING = True
    torch._dynamo.config.caching_precompile = True
    logging.getLogger("torch._dynamo.guards").addFilter(drop_precompile_guard_notices)
    # Dynamo names the globals a graph installs in its module from one counter that starts
    # at 0 in every process, and a loaded graph brings the names of the process that traced
    # it: two loaded graphs, or a loaded and a new one, can claim the same name ("Name
    # '__builtins_dict___2' already exists in scope") and the kernel then falls back to
    # eager. Numbering this process's graphs from a random 64-bit offset keeps them apart.
    from torch._dynamo import bytecode_transformation

    if hasattr(bytecode_transformation, "_unique_id_counter"):
        bytecode_transformation._unique_id_counter = itertools.count(secrets.randbits(64))
    atexit.register(_save_traced_graphs)


#: The message torch logs (as a warning) for every guard it leaves out of a graph kept by
#: the caching precompile: hundreds per job, none of them actionable.
PRECOMPILE_GUARD_NOTICE = "guard on %s is dropped with caching_precompile=True."


def drop_precompile_guard_notices(record: logging.LogRecord) -> bool:
    """Logging filter: False for torch's per-guard notice of the caching precompile
    (:data:`PRECOMPILE_GUARD_NOTICE`), True for every other record."""
    return not (isinstance(record.msg, str) and record.msg.endswith(PRECOMPILE_GUARD_NOTICE))


def _save_traced_graphs() -> None:
    try:
        torch.compiler.save_cache_artifacts()
    except Exception as exc:  # pragma: no cover - depends on the toolchain
        log.warning("could not keep the traced kernel graphs (%s); they will be traced again", exc)


def _compiled_or_eager(name: str, device: torch.device):
    fn = _KERNEL_FUNCTIONS[name]
    key = (device.type, name)
    if key in _COMPILE_FAILED:
        return fn
    if key not in _COMPILED:
        # dynamic shapes: one graph per (profile, table rows, dtype), whatever the
        # member and point counts; dynamo's default of 8 graphs per function would
        # silently fall back to eager in a process that renders many settings.
        dynamo_config = torch._dynamo.config
        dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, _MAX_KERNEL_GRAPHS)
        _COMPILED[key] = torch.compile(fn, dynamic=True, fullgraph=True)
    compiled = _COMPILED[key]

    def run(*args):
        if key in _COMPILE_FAILED:
            return fn(*args)
        try:
            return compiled(*args)
        except Exception as exc:  # pragma: no cover - depends on the toolchain
            log.warning(
                "torch.compile of the %s population kernel failed (%s); using eager", name, exc
            )
            _COMPILE_FAILED.add(key)
            return fn(*args)

    return run


def kernels_for(settings: RenderSettings, device: torch.device) -> Kernels:
    """Population kernels: torch.compile'd (``compile`` 'on', or 'auto' on a CPU with a
    C compiler) or eager (:mod:`subslope.physics.pairs.sums`)."""
    want = settings.compile == "on" or (settings.compile == "auto" and device.type == "cpu")
    if want and device.type == "cpu" and shutil.which("gcc") is None and shutil.which("cc") is None:
        want = False
    if not want:
        return Kernels(
            direct_sums,
            direct_sums_few,
            few_sums_with_sheet,
            far_sums,
            near_tile_sums,
            circle_peaks,
            False,
        )
    return Kernels(
        *(
            _compiled_or_eager(n, device)
            for n in ("direct", "few", "few_sheet", "far", "near", "peaks")
        ),
        True,
    )


def clear_cache() -> None:
    """Forget every compiled kernel and every recorded compile failure."""
    _COMPILED.clear()
    _COMPILE_FAILED.clear()
