"""Shared machinery of metrics whose state is pooled int64 counts plus a configuration."""

from __future__ import annotations

import copy
import hashlib
import json
import warnings
from collections.abc import Mapping
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

from dego.classes import CLASS_NAMES, NUM_CLASSES

_CONFIG_KEY = "_extra_state"
"""Where a persistent metric's configuration goes in ``state_dict`` (``nn.Module``'s extra-state
key, so that checkpoints saved before counts became opt-in still load)."""


DIGEST_BYTES = 16
"""Length of :func:`config_digest`."""


def config_digest(config: Mapping[str, Any]) -> tuple[int, ...]:
    """The first 16 bytes of the SHA-256 of ``config`` as canonical JSON, as ints 0..255.

    The same in every process (unlike Python's salted ``hash``), so ranks compare their
    configurations with it; small values, so a float comparison (torchmetrics' ``allclose``)
    still tells two digests apart.
    """
    text = json.dumps(config, sort_keys=True, default=str)
    return tuple(hashlib.sha256(text.encode()).digest()[:DIGEST_BYTES])


def _differences(mine: Mapping[str, Any], theirs: Mapping[str, Any]) -> str:
    """``"protocol 'occ3d' vs 'weak'"``: the keys where two configurations differ."""
    keys = [k for k in {**mine, **theirs} if mine.get(k) != theirs.get(k)]
    return ", ".join(f"{k} {mine.get(k)!r} vs {theirs.get(k)!r}" for k in keys)


def all_gather_json(value: Any, process_group: Any, device: torch.device) -> list[Any]:
    """Every rank's ``value`` (plain data), exchanged as JSON bytes: no pickle."""
    text = json.dumps(value, default=str)
    data = torch.tensor(list(text.encode()), dtype=torch.int64, device=device)
    size = torch.tensor([data.numel()], dtype=torch.int64, device=device)
    sizes = [torch.empty_like(size) for _ in range(dist.get_world_size(process_group))]
    dist.all_gather(sizes, size, group=process_group)
    longest = max(int(s) for s in sizes)
    padded = torch.zeros(longest, dtype=torch.int64, device=device)
    padded[: data.numel()] = data
    gathered = [torch.empty_like(padded) for _ in sizes]
    dist.all_gather(gathered, padded, group=process_group)
    return [
        json.loads(bytes(g[: int(s)].tolist()).decode())
        for g, s in zip(gathered, sizes, strict=True)
    ]


def gathered_if_different(value: Any, process_group: Any, device: torch.device) -> list[Any] | None:
    """Every rank's ``value`` (plain data, as JSON gives it back) when some rank's differs,
    else ``None``: one all-gather of a fixed-length digest, and the values themselves only
    when the digests differ. Every rank takes the same branch (each sees every digest)."""
    digest = torch.tensor(config_digest(value), dtype=torch.int64, device=device)
    digests = [torch.empty_like(digest) for _ in range(dist.get_world_size(process_group))]
    dist.all_gather(digests, digest, group=process_group)
    if all(torch.equal(d, digest) for d in digests):
        return None
    return all_gather_json(value, process_group, device)


def check_same_identity(identity: dict[str, Any], process_group: Any, device: torch.device) -> None:
    """Before counts are pooled across ranks: ``identity`` (``{"metric", "config",
    "counts"}``: the class, its configuration, the shapes of its counts) must be every
    rank's, else ``ValueError`` on every rank naming the other ranks' identities
    (:func:`gathered_if_different`)."""
    identity = json.loads(json.dumps(identity, default=str))  # as others see it
    identities = gathered_if_different(identity, process_group, device)
    if identities is None:
        return
    rank = dist.get_rank(process_group)

    def described(theirs: dict[str, Any]) -> str:
        kind = "" if theirs["metric"] == identity["metric"] else f"a {theirs['metric']} "
        mine = {"metric": identity["metric"], **identity["config"]}
        differences = _differences(mine, {"metric": theirs["metric"], **theirs["config"]})
        if not differences:  # only the shapes of the counts differ
            differences = _differences(identity["counts"], theirs["counts"])
        return f"{kind}{theirs['config']} ({differences})"

    others = [
        f"rank {r} has {described(ident)}"
        for r, ident in enumerate(identities)
        if r != rank and ident != identity
    ]
    raise ValueError(
        f"sync: the ranks of the process group hold {identity['metric']} with different "
        f"configurations, whose counts must not be pooled: this rank "
        f"({rank}) has {identity['config']}; {'; '.join(others)}. Configure the metric "
        "the same way on every rank"
    )


def class_names(num_classes: int) -> tuple[str, ...]:
    """Report names of ``num_classes`` labels: Occ3D-nuScenes' for 18, else ``class_<i>``."""
    if num_classes == NUM_CLASSES:
        return tuple(CLASS_NAMES)
    return tuple(f"class_{i}" for i in range(num_classes))


class CountingMetric(nn.Module):
    """Base class: int64 count buffers (named by ``COUNTS``) with torchmetrics-style
    ``merge / reset / sync / persistent`` and a configuration checked before anything is
    merged or loaded.

    The counts are evaluation state, not model state: by default they and the configuration
    stay out of ``state_dict``, so a model that holds a metric as a submodule saves and
    loads (``strict=True``) exactly as it would without it. :meth:`persistent` opts in.

    Subclasses register the buffers with :meth:`_add_count`, implement ``_config()`` and
    read their counts with ``_totals()`` (the synced totals after :meth:`sync`, else the
    local counts).
    """

    COUNTS: tuple[str, ...] = ()

    def __init__(self) -> None:
        super().__init__()
        self._synced: list[Tensor] | None = None
        self._persist = False

    def _add_count(self, name: str, count: Tensor) -> None:
        """Register an int64 count buffer (out of ``state_dict`` until :meth:`persistent`)."""
        self.register_buffer(name, count, persistent=self._persist)

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

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        """As torchmetrics' ``forward``: add the batch to the counts (``update``'s
        arguments) and return the batch's own value (``compute`` over that batch alone).
        ``metric(pred, gt, mask)`` in a loop therefore gives per-batch reports while the
        metric accumulates the whole run for ``compute()``."""
        batch: Any = copy.deepcopy(self)  # each subclass has its own update / compute
        batch.reset()
        batch.update(*args, **kwargs)
        self.merge(batch)
        return batch.compute()

    def reset(self) -> None:
        """Zero the counts."""
        for count in self._counts():
            count.zero_()
        self._changed()

    def sync(self, process_group: Any = None) -> CountingMetric:
        """All-reduce (sum) the counts over the ranks of ``process_group``; returns ``self``.

        A no-op when torch.distributed is not initialised. The configuration (and the
        shapes of the counts) is compared across the ranks first: if any rank's differs,
        every rank raises ``ValueError`` naming its own configuration and the other ranks',
        and nothing is pooled. The local counts are kept, so ``sync`` can be called again
        safely; ``compute`` uses the synced totals until the next ``update``, ``merge``,
        ``reset`` or ``load_state_dict``.
        """
        if not (dist.is_available() and dist.is_initialized()):
            return self
        counts = self._counts()
        device = counts[0].device
        if dist.get_backend(process_group) == "nccl" and device.type != "cuda":
            device = torch.device("cuda", torch.cuda.current_device())
        self._check_same_config_on_every_rank(process_group, device)
        state = torch.cat([c.reshape(-1) for c in counts]).to(device)
        dist.all_reduce(state, op=dist.ReduceOp.SUM, group=process_group)
        parts = state.to(counts[0].device).split([c.numel() for c in counts])
        self._synced = [p.view(c.shape) for p, c in zip(parts, counts, strict=True)]
        return self

    def _identity(self) -> dict[str, Any]:
        """What ranks must share to pool their counts: the class, the configuration and
        the shapes of the counts."""
        return {
            "metric": type(self).__name__,
            "config": self._config(),
            "counts": {name: list(getattr(self, name).shape) for name in self.COUNTS},
        }

    def _check_same_config_on_every_rank(self, process_group: Any, device: torch.device) -> None:
        check_same_identity(self._identity(), process_group, device)

    # -- (de)serialisation ------------------------------------------------------------
    def persistent(self, mode: bool = True) -> CountingMetric:
        """Save the counts and the configuration in ``state_dict`` (``mode=True``) or not
        (``False``, the default of a new metric); returns ``self``.

        torchmetrics' name for the same switch. A persistent metric saves its counts (keys
        ``<name>.<count>``) and configuration (``<name>._extra_state``), refuses a state
        saved under another configuration with ``ValueError`` and, with ``strict=True``,
        reports its keys as missing when a ``state_dict`` lacks them.
        """
        self._persist = bool(mode)
        for name in self.COUNTS:
            if self._persist:
                self._non_persistent_buffers_set.discard(name)
            else:
                self._non_persistent_buffers_set.add(name)
        return self

    def _check_saved_config(self, state: Any) -> None:
        if state != self._config():
            raise ValueError(
                f"state_dict: saved configuration {state} differs from {self._config()}"
            )

    def _save_to_state_dict(
        self, destination: dict[str, Any], prefix: str, keep_vars: bool
    ) -> None:
        super()._save_to_state_dict(destination, prefix, keep_vars)  # persistent buffers only
        if self._persist:
            destination[prefix + _CONFIG_KEY] = self._config()

    def _load_from_state_dict(
        self,
        state_dict: dict[str, Any],
        prefix: str,
        local_metadata: dict[str, Any],
        strict: bool,
        missing_keys: list[str],
        unexpected_keys: list[str],
        error_msgs: list[str],
    ) -> None:
        # Whatever the persistence, keys the metric once saved are its own (never
        # "unexpected"), and the configuration is checked before any count is overwritten,
        # so that a refused state_dict leaves this metric as it was.
        config_key = prefix + _CONFIG_KEY
        keys = {name: prefix + name for name in self.COUNTS}
        if config_key in state_dict:
            saved = state_dict.pop(config_key)
            if saved != self._config():
                if self._persist:
                    self._check_saved_config(saved)
                warnings.warn(
                    f"state_dict: saved configuration {saved} differs from {self._config()}; "
                    f"the saved counts of {prefix.rstrip('.') or type(self).__name__!r} are "
                    "ignored (its counts are not persistent; call .persistent() to make this "
                    "an error)",
                    UserWarning,
                    stacklevel=4,
                )
                for key in keys.values():
                    state_dict.pop(key, None)
        elif self._persist and strict:
            missing_keys.append(config_key)
        if not self._persist:  # non-persistent buffers: torch would skip them, load them here
            for name, key in keys.items():
                if key not in state_dict:
                    continue
                value, count = state_dict.pop(key), getattr(self, name)
                if not isinstance(value, Tensor) or value.shape != count.shape:
                    shape = tuple(value.shape) if isinstance(value, Tensor) else type(value)
                    error_msgs.append(
                        f"size mismatch for {key}: copying a count of shape {shape} from the "
                        f"checkpoint, the shape in the current metric is {tuple(count.shape)}."
                    )
                    continue
                with torch.no_grad():
                    count.copy_(value)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        self._changed()


__all__ = ["DIGEST_BYTES", "CountingMetric", "config_digest"]
