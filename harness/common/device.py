"""Where a run computes: `device=cpu` (the default, and the tests'), `cuda`, or `auto` (CUDA when
present). On CUDA the forward passes run under bf16 autocast; on the CPU nothing changes."""

from __future__ import annotations

import contextlib

import torch

from harness.common.errors import RetainError

DEVICES = ("cpu", "cuda", "auto")


def resolve_device(name: str, cuda_available: bool | None = None) -> torch.device:
    """The torch device for a `device=` setting; a one-line error for a bad or absent one."""
    available = torch.cuda.is_available() if cuda_available is None else cuda_available
    if name not in DEVICES and not name.startswith("cuda:"):
        raise RetainError(f"unknown device {name!r}; valid: {', '.join(DEVICES)} or cuda:N")
    if name == "auto":
        return torch.device("cuda" if available else "cpu")
    if name.startswith("cuda") and not available:
        raise RetainError(f"device={name} but torch sees no CUDA GPU; use device=cpu or auto")
    return torch.device(name)


def autocast(device: torch.device):
    """bf16 autocast on CUDA; a no-op context elsewhere (CPU results stay bit-identical)."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()
