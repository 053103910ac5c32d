"""Every example script runs: each examples/*.py in a subprocess with a tiny budget."""

from __future__ import annotations

import importlib.util
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from dego.cli import main as dego_main
from tests.helpers.repo import ROOT, needs_source_tree

TMP = "{tmp}"  # replaced by the test's tmp_path

# The arguments of every script (a new script needs an entry here: see the test below).
ARGUMENTS: dict[str, list[str]] = {
    "quickstart.py": [],
    "evaluate_occ3d.py": ["--scenes", "1", "--frames", "2", "--out", f"{TMP}/report.json"],
    "train_ddp.py": [
        *("--steps", "3", "--scenes", "2", "--val-scenes", "1", "--frames", "1"),
        *("--device", "cpu", "--out", TMP),
    ],
    "porting.py": ["--gaussians", "1500"],
    "fit_scene.py": ["--iterations", "3", "--gaussians", "400", "--frames", "2", "--out", TMP],
    "train_feedforward.py": [
        *("--steps", "3", "--train-scenes", "2", "--heldout-scenes", "1"),
        *("--image-size", "16", "48", "--cache", TMP),
    ],
}
# Scripts run by a test of their own (needing an extra), not by test_example_runs.
TESTED_ELSEWHERE: dict[str, str] = {"train_lightning.py": "tests/test_example_lightning.py"}
# Scripts started by a launcher instead of plain `python`.
LAUNCHERS: dict[str, list[str]] = {
    "train_ddp.py": ["-m", "torch.distributed.run", "--nproc_per_node", "2", "--standalone"],
}
TIMEOUT_S = 300


def run_example(name: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    assert ROOT is not None
    args = [arg.replace(TMP, str(tmp_path)) for arg in ARGUMENTS[name]]
    command = [sys.executable, *LAUNCHERS.get(name, []), str(ROOT / "examples" / name), *args]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    result = subprocess.run(
        command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT_S
    )
    assert result.returncode == 0, (
        f"{' '.join(command)} exited with {result.returncode}\n"
        f"--- stdout ---\n{result.stdout[-4000:]}\n--- stderr ---\n{result.stderr[-4000:]}"
    )
    assert result.stdout.strip(), f"{name} printed nothing"
    return result


def test_every_example_has_arguments(source_tree: Path) -> None:
    scripts = {path.name for path in (source_tree / "examples").glob("*.py")}
    missing = sorted(scripts - ARGUMENTS.keys() - TESTED_ELSEWHERE.keys())
    assert not missing, f"add the arguments of {missing} to ARGUMENTS in {Path(__file__).name}"


@pytest.mark.slow
@needs_source_tree
@pytest.mark.parametrize("name", sorted(ARGUMENTS))
def test_example_runs(name: str, tmp_path: Path) -> None:
    assert ROOT is not None and (ROOT / "examples" / name).is_file(), f"examples/{name} is missing"
    result = run_example(name, tmp_path)

    if name == "evaluate_occ3d.py":
        report = json.loads((tmp_path / "report.json").read_text())
        assert report["samples"] == 2
        assert {"occ3d", "weak", "rayiou"} <= report.keys()
        assert "protocol: occ3d" in result.stdout and "protocol: weak" in result.stdout
        assert "RayIoU" in result.stdout
    if name == "train_feedforward.py":
        assert "step    2" in result.stdout and "mIoU" in result.stdout
        assert list(Path(tmp_path).glob("scenes-*/scene-*.npz"))  # cached where told
    if name == "train_ddp.py":
        out = result.stdout
        assert "2 rank(s), backend gloo" in out
        assert "step    3/3" in out
        # rank 0 printed the synced metrics, once
        assert out.count("protocol: weak") == 1
        assert "mIoU" in out and "RayIoU" in out
        metrics = json.loads((tmp_path / "metrics.json").read_text())
        assert {"miou", "iou", "rayiou"} <= metrics.keys() and metrics["units"] == "fraction"
        assert all(0 <= metrics[k] <= 1 for k in ("miou", "iou", "rayiou"))
        assert (tmp_path / "model.pt").is_file()


@pytest.mark.slow
def test_evaluate_demo_dir_prints_the_matching_dego_eval(
    source_tree: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With --demo-dir the demo data outlives the script, which prints the `dego eval` command
    that scores it; that command, run as printed, gives the script's scores."""
    spec = importlib.util.spec_from_file_location(
        "evaluate_occ3d_example", source_tree / "examples" / "evaluate_occ3d.py"
    )
    assert spec is not None and spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    demo = tmp_path / "demo data"  # a space: the printed command must quote it
    argv = ["--scenes", "1", "--frames", "2", "--demo-dir", str(demo)]
    assert example.main([*argv, "--out", str(tmp_path / "script.json")]) == 0
    prefix = "the same from the command line: "
    printed = [line for line in capsys.readouterr().out.splitlines() if line.startswith(prefix)]
    assert len(printed) == 1, printed
    words = shlex.split(printed[0].removeprefix(prefix))
    assert words[:2] == ["dego", "eval"]
    assert words[words.index("--gt") + 1] == str(demo / "gt")
    assert words[words.index("--pred") + 1] == str(demo / "pred")
    assert words[words.index("--infos") + 1] == str(demo / "nuscenes_infos_val.pkl")

    assert dego_main([*words[1:], "--quiet", "--json", str(tmp_path / "cli.json")]) == 0
    script, cli = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("script", "cli"))
    assert script["samples"] == cli["samples"] == 2
    for key in ("occ3d", "weak", "rayiou"):
        assert script[key] == cli[key], key

    # without --demo-dir the data goes with its temporary folder: no command to print
    assert example.main(["--scenes", "1", "--frames", "1", "--no-rayiou"]) == 0
    assert prefix not in capsys.readouterr().out
