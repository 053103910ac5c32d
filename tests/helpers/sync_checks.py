"""Checks shared by the 2-rank tests of ``sync`` between differently configured ranks."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from torch import Tensor


def assert_refused_on_every_rank(
    results: list[dict[str, Any]], cases: Iterable[str], merged_per_class: Tensor
) -> None:
    """Each rank's error for each case names its own configuration and the other rank's;
    the well-configured sync after the refusals equals one process's merge of both ranks."""
    cases = list(cases)
    for rank, result in enumerate(results):
        other = results[1 - rank]
        for case in cases:
            error = result[case]
            assert error.startswith("ValueError: sync:"), (case, rank, error)
            assert f"this rank ({rank}) has {result[case + '/config']}" in error, (case, error)
            assert f"rank {1 - rank} has {other[case + '/config']}" in error, (case, error)
        np.testing.assert_array_equal(result["after"].numpy(), merged_per_class.numpy())
