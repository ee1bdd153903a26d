"""The one device chooser: every job picks its torch device here, at run time.

``None`` or ``"auto"`` means CUDA when this process sees a CUDA device, else the CPU;
any other name (``"cpu"``, ``"cuda"``, ``"cuda:1"``) is taken as given, after checking
that the machine can serve it, so a CUDA request on a CPU-only machine fails before any
work with a message that names the config key it came from.
"""

from __future__ import annotations

__all__ = ["DeviceError", "pick_device"]


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
