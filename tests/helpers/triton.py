"""Where ``backend="triton"`` can run in this test process: with triton installed, on CUDA
when a GPU is present, on CPU through Triton's interpreter (tests/conftest.py turns it on
where no GPU is present, before dego first imports its kernels)."""

from __future__ import annotations

import importlib.util

import pytest
import torch

INSTALLED = importlib.util.find_spec("triton") is not None
NOT_INSTALLED = "needs triton (the `triton` extra)"


def why_not(device: str) -> str | None:
    """Why the Triton backend cannot run on ``device`` here, or ``None`` when it can."""
    if not INSTALLED:
        return NOT_INSTALLED
    if device == "cuda":
        return None if torch.cuda.is_available() else "CUDA not available"
    from dego.splatting import triton_backend

    if triton_backend.interpreting():
        return None
    return "Triton's interpreter is off (TRITON_INTERPRET=1 not set before the import)"


def on(device: str) -> pytest.MarkDecorator:
    """Skip unless the Triton backend runs on ``device``."""
    reason = why_not(device)
    return pytest.mark.skipif(reason is not None, reason=reason or "")
