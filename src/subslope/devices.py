"""The one device chooser: every job picks its torch device here, at run time.

``None`` or ``"auto"`` means CUDA when this process sees a CUDA device, else the CPU;
any other name (``"cpu"``, ``"cuda"``, ``"cuda:1"``) is taken as given, after checking
that the machine can serve it, so a CUDA request on a CPU-only machine fails before any
work with a message that names the config key it came from.
"""

from __future__ import annotations

__all__ = ["DEVICE_KEYS", "DeviceError", "device_problems", "machine_description", "pick_device"]

#: The config keys that name a torch device, with the stage whose jobs use each.
DEVICE_KEYS = {
    "simulation.render.device": "simulate",
    "training.device": "train",
    "inference.device": "evaluate",
}


class DeviceError(RuntimeError):
    """The requested device does not exist on this machine."""


def pick_device(name=None, *, key: str | None = None):
    """A ``torch.device`` for ``name`` (``None``/``"auto"``: CUDA if available, else CPU).

    ``key`` names the config key the request came from, for the error message.
    """
    import torch

    if isinstance(name, torch.device):
        name = str(name)
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        where = f"config key {key} = {name!r}" if key else f"device {name!r}"
        raise DeviceError(
            f"{where}: this machine has no CUDA device (torch {torch.__version__}, "
            f"CUDA build: {torch.version.cuda or 'none'}); use 'cpu' or 'auto'"
        )
    return device


def device_problems(config, stages=None) -> list[str]:
    """The device requests of ``config`` (:data:`DEVICE_KEYS`) this machine cannot serve,
    one message per key, for the stages that run (``stages``: ``{stage: runs}``, default
    all). Only a request for CUDA imports torch, so a config of ``auto``/``cpu`` devices is
    checked without it. The workflow calls this when it loads for a local run; on a
    cluster the job checks its own device when it starts (:func:`pick_device`)."""
    problems = []
    for key, stage in DEVICE_KEYS.items():
        if stages is not None and not stages.get(stage, True):
            continue
        section, _, name = key.rpartition(".")
        node = config
        for part in section.split("."):
            node = node.get(part, {})
        value = node.get(name)
        if isinstance(value, str) and value.startswith("cuda"):
            try:
                pick_device(value, key=key)
            except DeviceError as exc:
                problems.append(str(exc))
    return problems


def machine_description() -> dict[str, object]:
    """This machine as a campaign record states it: CPU model (``/proc/cpuinfo``), cores,
    the CUDA device's name if any, Python and torch versions."""
    import os
    import platform

    import torch

    cpu = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            cpu = next(
                (line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")),
                cpu,
            )
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "gpu": gpu,
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
