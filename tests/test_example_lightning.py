"""examples/train_lightning.py with the real Lightning and torchmetrics (the `lightning` extra):
a few compiled steps under bf16 autocast, both dego metrics logged and written out."""

from __future__ import annotations

import csv
import importlib.util
import json
import logging
import math
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import torch
import torch._dynamo

pytest.importorskip("lightning")
pytest.importorskip("torchmetrics")

from dego.splatting import composite

STEPS = 3
ARGV = [
    *("--steps", str(STEPS), "--gaussians", "300", "--frames", "2", "--image-size", "32", "88"),
    *("--compile-backend", "eager", "--precision", "bf16-mixed"),
]


@pytest.fixture
def example(source_tree: Path) -> Iterator[ModuleType]:
    """The example script as a module (it is not a package), with fresh dynamo caches."""
    path = source_tree / "examples" / "train_lightning.py"
    spec = importlib.util.spec_from_file_location("train_lightning_example", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    torch._dynamo.reset()
    yield module
    torch._dynamo.reset()


class _Records(logging.Handler):
    """Keeps the messages of the records it handles."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _from_dego(text: str) -> bool:
    """Whether a warning or log message points into dego's own files."""
    source = str(Path(composite.__file__).resolve().parents[1])
    return source in text or "src/dego/" in text or "site-packages/dego/" in text


@pytest.mark.slow
def test_compiled_bf16_fit_logs_both_metrics(example: ModuleType, tmp_path: Path) -> None:
    kernels = composite.COMPILED_KERNELS
    dynamo_log = _Records()  # dynamo reports graph breaks on its logger, not as warnings
    logging.getLogger("torch._dynamo").addHandler(dynamo_log)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            summary = example.main([*ARGV, "--out", str(tmp_path)])
    finally:
        logging.getLogger("torch._dynamo").removeHandler(dynamo_log)
    assert composite.COMPILED_KERNELS == kernels  # the example restores dego's setting
    # the example runs clean: no warning from dego's files, no graph break anywhere
    ours = [str(w.message) for w in caught if _from_dego(f"{w.filename} {w.message}")]
    assert not ours, ours[0]
    breaks = [m for m in dynamo_log.messages if "Graph break" in m]
    assert not breaks, breaks[0]

    # every step ran the torch.compile'd loss function (no eager fallback) under bf16 autocast
    assert summary["compiled_steps"] == STEPS
    assert summary["autocast"] == ["torch.bfloat16"]
    for term, values in summary["losses"].items():
        assert len(values) == STEPS, term
        assert all(math.isfinite(v) for v in values), (term, values)
    assert summary["losses"]["total"][0] > 0

    # the JSON summary: both metrics as fractions, equal to what Lightning logged (a key
    # holds one unit everywhere)
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["units"] == "fraction"
    assert written["settings"]["compile_backend"] == "eager"
    for name in ("initial", "final"):
        for key in ("miou", "rayiou"):
            assert 0 <= written[name][key] <= 1, (name, key, written[name])
    for key in ("miou", "rayiou"):
        assert written["logged"][f"val/{key}"] == pytest.approx(written["final"][key], abs=1e-5)
    # Lightning reset the metrics between the two validation runs: the scores differ
    assert written["initial"] != written["final"]

    # Lightning's CSV log holds the training loss and both validation metrics
    (log,) = tmp_path.glob("lightning/version_0/metrics.csv")
    rows = list(csv.DictReader(log.open()))
    losses = [float(r["train/loss"]) for r in rows if r.get("train/loss")]
    assert losses and all(math.isfinite(v) for v in losses)
    assert sum(1 for r in rows if r.get("val/miou")) == 2
    assert sum(1 for r in rows if r.get("val/rayiou")) == 2
    final_row = [r for r in rows if r.get("val/miou")][-1]  # the same number under the same key
    assert float(final_row["val/miou"]) == pytest.approx(written["logged"]["val/miou"], abs=1e-6)
