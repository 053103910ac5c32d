"""Shared machinery of metrics whose state is pooled int64 counts plus a configuration."""

from __future__ import annotations

from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn


class CountingMetric(nn.Module):
    """Base class: int64 count buffers (named by ``COUNTS``) with torchmetrics-style
    ``merge / reset / sync`` and a configuration saved in ``state_dict`` (as extra state)
    and checked before anything is loaded or merged.

    Subclasses register the buffers, implement ``_config()`` and read their counts with
    ``_totals()`` (the synced totals after :meth:`sync`, else the local counts).
    """

    COUNTS: tuple[str, ...] = ()

    def __init__(self) -> None:
        super().__init__()
        self._synced: list[Tensor] | None = None

    def _config(self) -> dict[str, Any]:
        raise NotImplementedError

    def _counts(self) -> list[Tensor]:
        return [getattr(self, name) for name in self.COUNTS]

    def _totals(self) -> list[Tensor]:
        return self._synced or self._counts()

    def _changed(self) -> None:
        """Forget synced totals: call after every change of the local counts."""
        self._synced = None

    def merge(self, other: CountingMetric) -> CountingMetric:
        """Add another instance's counts into this one (same configuration); returns ``self``."""
        if type(other) is not type(self):
            raise TypeError(f"other: expected {type(self).__name__}, got {type(other).__name__}")
        if other._config() != self._config():
            raise ValueError(
                f"other: configuration {other._config()} differs from {self._config()}"
            )
        for mine, theirs in zip(self._counts(), other._counts(), strict=True):
            mine += theirs.to(mine.device)
        self._changed()
        return self

    def reset(self) -> None:
        """Zero the counts."""
        for count in self._counts():
            count.zero_()
        self._changed()

    def sync(self, process_group: Any = None) -> CountingMetric:
        """All-reduce (sum) the counts over the ranks of ``process_group``; returns ``self``.

        A no-op when torch.distributed is not initialised. The local counts are kept, so
        ``sync`` can be called again safely; ``compute`` uses the synced totals until the
        next ``update``, ``merge``, ``reset`` or ``load_state_dict``.
        """
        if not (dist.is_available() and dist.is_initialized()):
            return self
        counts = self._counts()
        state = torch.cat([c.reshape(-1) for c in counts])
        if dist.get_backend(process_group) == "nccl" and state.device.type != "cuda":
            state = state.to(torch.device("cuda", torch.cuda.current_device()))
        dist.all_reduce(state, op=dist.ReduceOp.SUM, group=process_group)
        parts = state.to(counts[0].device).split([c.numel() for c in counts])
        self._synced = [p.view(c.shape) for p, c in zip(parts, counts, strict=True)]
        return self

    # -- (de)serialisation ------------------------------------------------------------
    def get_extra_state(self) -> dict[str, Any]:
        return self._config()

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self._check_saved_config(state)
        self._changed()

    def _check_saved_config(self, state: Any) -> None:
        if state != self._config():
            raise ValueError(
                f"state_dict: saved configuration {state} differs from {self._config()}"
            )

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        # Check the configuration before any count is overwritten, so that a refused
        # state_dict leaves this metric as it was.
        key = prefix + "_extra_state"
        if key in state_dict:
            self._check_saved_config(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args)


__all__ = ["CountingMetric"]
