"""Read a ``.rrd`` recording back with rerun's own reader (its catalog / dataframe API)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def read_recording(path: Path, index: str | None = "frame") -> dict[str, list[Any]]:
    """The recording at ``path`` as ``column name: values``, one row per time on ``index``
    (``None``: the static data); rows ordered by time. Served by ``rerun.server.Server`` on
    loopback, read through its DataFusion reader."""
    import rerun as rr

    with rr.server.Server(host="127.0.0.1", datasets={"recording": [str(path)]}) as server:
        dataset = server.client().get_dataset("recording")
        table = dataset.reader(index=index).to_arrow_table()
    columns = table.to_pydict()
    if index is None:
        return columns
    order = sorted(range(table.num_rows), key=lambda row: columns[index][row])
    return {name: [values[row] for row in order] for name, values in columns.items()}


def column(columns: dict[str, list[Any]], entity: str, component: str) -> list[Any]:
    """The values of ``<entity>:<component>`` (e.g. ``"world/occ"``, ``"VoxelGridMap:colors"``),
    one per row (``None`` where the row has none)."""
    name = f"/{entity.strip('/')}:{component}"
    if name not in columns:
        raise KeyError(f"{name} not in the recording; it has {sorted(columns)}")
    return columns[name]
