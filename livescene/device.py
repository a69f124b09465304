"""Device choice: CUDA when present (auto), CPU otherwise; a clear error when CUDA is asked for and absent."""

from __future__ import annotations

import torch

from .errors import LiveSceneError


def select_device(name: str | torch.device | None = "auto") -> torch.device:
    if isinstance(name, torch.device):
        return name
    name = (name or "auto").lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise LiveSceneError("--device cuda was asked for but torch sees no CUDA device; use --device cpu or auto")
        return torch.device(name)
    if name == "cpu":
        return torch.device("cpu")
    raise LiveSceneError(f"unknown device {name!r}: use auto, cpu or cuda")


def describe(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return f"cpu ({torch.get_num_threads()} threads)"


def configure_threads(threads: int = 0) -> int:
    """Set torch's CPU threads. 0 = auto: all cores, or 1 when the machine is already busy (load average above
    half the cores): OpenMP workers that wait on descheduled siblings made a shared 2-core machine 10-100x
    slower per step than one thread. Returns the number used."""
    import os

    if threads <= 0:
        cores = os.cpu_count() or 1
        try:
            busy = os.getloadavg()[0] > 0.5 * cores
        except OSError:
            busy = False
        threads = 1 if busy else cores
    torch.set_num_threads(threads)
    return threads
