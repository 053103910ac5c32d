"""Shared pytest configuration: hypothesis profiles, markers, the device/dtype fixtures and the
`source_tree` fixture (the repository root; skips when the tests run from a copy)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, settings

# Before the first import of them: pytest rewrites the asserts of test modules only.
pytest.register_assert_rewrite("tests.helpers", "tests.reference")

from tests.helpers.repo import ROOT, SLOW_MARKER, SOURCE_TREE_REASON  # noqa: E402

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Under pytest-xdist every worker (and every process a test starts) computes on one
    # thread: two workers with a torch pool each on two cores spin against each other.
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)

# The Triton backend's tests run its kernels on CPU through Triton's interpreter where no GPU
# is present; the variable must be set before dego first imports its kernels.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

settings.register_profile(
    "default",
    deadline=None,
    max_examples=60,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("ci", parent=settings.get_profile("default"), derandomize=True)
settings.register_profile("thorough", parent=settings.get_profile("default"), max_examples=1000)
settings.load_profile(
    os.environ.get("DEGO_HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "default")
)


def pytest_configure(config: pytest.Config) -> None:
    # Also in pyproject.toml; registered here for runs from a copy of tests/ (no pyproject there,
    # and `--strict-markers` would reject the marker).
    config.addinivalue_line("markers", SLOW_MARKER)


@pytest.fixture(scope="session")
def source_tree() -> Path:
    """The repository root; the test skips when the tests run outside it (a copy of tests/)."""
    if ROOT is None:
        pytest.skip(SOURCE_TREE_REASON)
    return ROOT


DEVICES = [
    "cpu",
    pytest.param(
        "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
    ),
]
DTYPES = [torch.float32, torch.float64]


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    return request.param
