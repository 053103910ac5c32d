"""``dego train``: bad flags are usage errors before any work; --quick runs every variant."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch

import dego.demo.feedforward.command as command
from dego.cli import main
from dego.demo.feedforward import FEEDFORWARD_VARIANTS, SCORES, load_scenes
from dego.demo.feedforward.study import (
    COMPARISONS,
    PRESETS,
    FeedForwardRuns,
    FeedForwardStudyConfig,
    feedforward_report,
    won_back,
)
from dego.demo.stats import StudyRun
from tests.helpers.cli_faults import FullDisk, ReadOnly
from tests.helpers.feedforward import render_tiny


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def started(*args: object, **kwargs: object) -> None:
        raise AssertionError("the study started")

    monkeypatch.setattr(command, "run_feedforward_study", started)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--steps", "-1"], "argument --steps"),
        (["--steps", "ten"], "argument --steps"),
        (["--seeds", "2-1"], "argument --seeds"),
        (["--seeds", "0,0"], "argument --seeds"),
        (["--variants", "static,warp"], "--variants: unknown ['warp']"),
        (["--variants", "static,static"], "argument --variants"),
        (["--train-scenes", "0"], "argument --train-scenes"),
        (["--heldout-scenes", "x"], "argument --heldout-scenes"),
        (["--quick", "--full"], "not allowed with argument"),
        (["--device", "tpu"], "argument --device"),
        (["--frame-dt", "0"], "argument --frame-dt"),
        (["--frame-dt", "-1"], "argument --frame-dt"),
        (["--frame-dt", "nan"], "argument --frame-dt"),
        (["--frame-dt", "inf"], "argument --frame-dt"),
        (["--frame-dt", "9"], "argument --frame-dt"),
        (["--frame-dt", "fast"], "argument --frame-dt"),
        (["--frames", "4"], "--frames: expected an odd number"),
        (["--frames", "2"], "argument --frames"),
        (["--frames", "81"], "--frame-dt:"),  # 40 frames of 0.5 s: 20 s > 8 s
        (["--frames", "35", "--frame-dt", "0.5"], "--frame-dt:"),
        (["--depth", "foo"], "argument --depth"),
        (["--recipe", "foo"], "argument --recipe"),
        (["--depth-noise", "1"], "argument --depth-noise"),
        (["--depth-noise", "-0.1"], "argument --depth-noise"),
        (["--depth-noise", "nan"], "argument --depth-noise"),
        (["--warmup-steps", "-1"], "argument --warmup-steps"),
    ],
)
def test_bad_flags_are_usage_errors_before_any_work(
    flags: list[str],
    message: str,
    tmp_path: Path,
    no_work: None,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out, cache = tmp_path / "out", tmp_path / "cache"
    with pytest.raises(SystemExit) as exit_info:
        main(["train", *flags, "--cache", str(cache), "--out", str(out)])
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("dego train: error:") and message in line, line
    assert not out.exists() and not cache.exists()


@pytest.mark.parametrize("flag", ["--cache", "--out"])
def test_an_unwritable_cache_or_out_is_a_usage_error(
    flag: str, tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("in the way")  # a folder below a file cannot exist, root or not
    target = {"--cache": tmp_path / "cache", "--out": tmp_path / "out", flag: blocker / "x"}
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--cache", str(target["--cache"]), "--out", str(target["--out"])])
    assert exit_info.value.code == 2
    assert f"error: {flag}:" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


# -- file faults: outputs checked first, the cache's failures survived, the end all or nothing


SCENES = [11, 12, 13]
"""The scenes the stand-in study loads (rendered as tiny records)."""

QUICK = ["train", "--quick", "--variants", "static,rigid"]


def _stand_in_study(
    monkeypatch: pytest.MonkeyPatch, during: Callable[[], object] | None = None
) -> list[int]:
    """``dego train``'s work replaced by: load :data:`SCENES` through the cache (rendered
    as tiny records), call ``during()``, return one seed's made-up scores. Returns the seeds
    rendered."""
    rendered = render_tiny(monkeypatch)

    def study(config: FeedForwardStudyConfig, *, cache: Path | None, **kwargs: object) -> object:
        load_scenes(SCENES, config.data, cache)
        if during is not None:
            during()
        return _runs({variant: [1.0] for variant in config.variants})

    monkeypatch.setattr(command, "run_feedforward_study", study)
    return rendered


def _previous_outputs(out: Path) -> dict[str, bytes]:
    out.mkdir(parents=True, exist_ok=True)
    for name in ("train.md", "train.json"):
        (out / name).write_text(f"previous {name}\n")
    return _contents(out)


def _contents(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in folder.iterdir() if path.is_file()}


@pytest.mark.parametrize("taken", ["heldout_rigid.png", "train.json"])
def test_an_output_name_taken_by_a_folder_is_a_usage_error_before_any_work(
    taken: str, tmp_path: Path, no_work: None, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: the run went to the end, then train.md (and train.json) were replaced and the
    rename onto heldout_rigid.png failed with a traceback: half-new outputs."""
    out = tmp_path / "out"
    before = _previous_outputs(out)
    (out / taken).unlink(missing_ok=True)
    (out / taken).mkdir()
    before.pop(taken, None)
    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, "--cache", str(tmp_path / "cache"), "--out", str(out)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    line = err.strip().splitlines()[-1]
    assert line == f"dego train: error: --out: {out / taken} is a directory, expected a file name"
    assert "Traceback" not in err and _contents(out) == before
    if taken.endswith(".png"):  # without pictures that name is no output: the work starts
        with pytest.raises(AssertionError, match="the study started"):
            main([*QUICK, "--no-pictures", "--no-cache", "--out", str(out)])


@pytest.mark.parametrize(
    "fault", ["full disk", "folder is a file", "folder is read-only", "scene is a folder"]
)
def test_a_cache_that_cannot_be_written_is_a_warning_and_the_run_goes_on(
    fault: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: an OSError traceback, the run lost."""
    cache, out = tmp_path / "cache", tmp_path / "out"
    folder = cache / f"scenes-{PRESETS['quick'].data.digest()}"
    rendered = _stand_in_study(monkeypatch)
    if fault == "full disk":
        FullDisk(monkeypatch, cache.resolve(), fail_at=1)  # the first scene written
    elif fault == "folder is a file":
        cache.mkdir()
        folder.write_text("in the way\n")
    elif fault == "folder is read-only":
        folder.mkdir(parents=True)
        ReadOnly(monkeypatch, folder)
    else:
        (folder / f"scene-{SCENES[0]}.npz").mkdir(parents=True)
    with pytest.warns(UserWarning) as warned:
        code = main([*QUICK, "--no-pictures", "--cache", str(cache), "--out", str(out)])
    assert code == 0
    messages = [str(w.message) for w in warned]
    cannot = [m for m in messages if "cannot cache the scene" in m]
    assert len(cannot) == 1 and cannot[0].endswith("; going on without caching"), messages
    assert cannot[0].startswith(f"{folder / f'scene-{SCENES[0]}.npz'}: ")
    reason = {
        "full disk": "No space left on device",
        "folder is a file": "File exists",
        "folder is read-only": "Permission denied",
        "scene is a folder": "Is a directory",
    }[fault]
    assert f"({reason}" in cannot[0]
    if fault == "scene is a folder":
        assert any("unusable cached scene" in m for m in messages)
    assert rendered == SCENES  # every scene, each once; nothing cached after the failure
    if folder.is_dir():
        assert [p.name for p in folder.iterdir() if p.is_file()] == []  # no temporary file
    assert json.loads((out / "train.json").read_text())["settings"]["variants"] == [
        "static",
        "rigid",
    ]
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("fault", ["full disk", "made read-only during the run"])
def test_outputs_that_cannot_be_written_are_one_error_line_and_the_old_files_stay(
    fault: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: an OSError traceback (exit 1)."""
    out = tmp_path / "out"
    before = _previous_outputs(out)
    if fault == "full disk":
        _stand_in_study(monkeypatch)
        FullDisk(monkeypatch, out.resolve())  # the second file written: train.json
        reason = "No space left on device"
    else:
        _stand_in_study(monkeypatch, during=lambda: ReadOnly(monkeypatch, out))
        reason = "Permission denied"
    code = main([*QUICK, "--no-pictures", "--no-cache", "--out", str(out)])
    assert code == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot write {out}/train."), err
    assert f": {reason}; the previous files in {out} are as they were" in lines[0]
    monkeypatch.undo()
    assert _contents(out) == before and sorted(p.name for p in out.iterdir()) == sorted(before)


def test_the_printed_total_is_the_whole_command_the_report_and_pictures_included(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 51: ``total`` stopped before the report and pictures were written (195 s
    printed, 301 s taken), where ``dego demo`` and ``dego study`` count them. A clock that
    the stand-in study moves 100 s and the writing 200 s: total 300 s, the report's own
    wall time (written before its writing ends) 100 s."""
    offset = [0.0]
    perf_counter = time.perf_counter
    monkeypatch.setattr(time, "perf_counter", lambda: perf_counter() + offset[0])

    def advance(seconds: float) -> None:
        offset[0] += seconds

    _stand_in_study(monkeypatch, during=lambda: advance(100.0))
    write = command.write_feedforward_study

    def slow_write(*args: Any, **kwargs: Any) -> Any:
        advance(200.0)  # the report and the pictures
        return write(*args, **kwargs)

    monkeypatch.setattr(command, "write_feedforward_study", slow_write)
    out = tmp_path / "out"
    assert main([*QUICK, "--no-pictures", "--no-cache", "--out", str(out)]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("total ") and last.endswith(" s"), last
    assert 300.0 <= float(last.split()[1]) < 360.0, last
    wall = json.loads((out / "train.json").read_text())["settings"]["wall_seconds"]
    assert 100.0 <= wall < 160.0


def test_presets_and_flags_make_the_study_asked_for() -> None:
    train = command.add_arguments(argparse.ArgumentParser())
    args = train.parse_args(["--full", "--steps", "7", "--variants", "static,decoupled"])
    config = command.study_config(args)
    assert config.seeds == PRESETS["full"].seeds and len(config.seeds) >= 3
    assert config.train.steps == 7 and config.variants == ("static", "decoupled")
    assert command.study_config(train.parse_args([])) == PRESETS["cpu"]
    assert PRESETS["cpu"].variants == FEEDFORWARD_VARIANTS
    flags = [
        *("--warmup-steps", "5", "--recipe", "scratch", "--depth", "learned"),
        *("--frames", "5", "--frame-dt", "0.2", "--depth-noise", "0.1", "--quick"),
    ]
    config = command.study_config(train.parse_args(flags))
    assert (config.train.warmup_steps, config.train.recipe) == (5, "scratch")
    assert config.train.depth_source == "learned"
    assert config.train.steps == PRESETS["quick"].train.steps
    assert (config.data.frames, config.data.frame_dt, config.data.depth_noise) == (5, 0.2, 0.1)
    assert config.data.image_size == PRESETS["quick"].data.image_size
    assert command.study_config(train.parse_args(["--frame-dt", "8"])).data.frame_dt == 8.0


def _runs(values: dict[str, list[float]]) -> FeedForwardRuns:
    runs = [
        StudyRun(seed, 100, variant, dict.fromkeys(SCORES, v), {}, float("nan"), 1.0)
        for variant, per_seed in values.items()
        for seed, v in enumerate(per_seed)
    ]  # fmt: skip
    return FeedForwardRuns(runs, {}, None, 0.0)


def test_the_report_gives_intervals_and_answers_the_questions() -> None:
    result = _runs(
        {
            "single-frame": [10.0, 11.0, 12.0],
            "static": [8.0, 9.0, 10.5],
            "decoupled": [9.0, 10.0, 11.0],
            "true-motion": [12.0, 13.0, 14.0],
        }
    )
    config = FeedForwardStudyConfig(
        seeds=(0, 1, 2), variants=("single-frame", "static", "decoupled", "true-motion")
    )
    text, payload = feedforward_report(result, config, wall_seconds=12.0, device="cpu")
    assert "| static | 9.17 [" in text
    assert "| 0 | 10.0 / 10.0 / 10.0 / 10.0 | 8.0 / 8.0 / 8.0 / 8.0 |" in text  # per seed
    assert "static - single-frame on HCM at t = 0: -1.83 [" in text
    assert "the interval excludes 0 (negative)" in text
    paired = payload["paired"]["true-motion - static: HCM"]
    assert paired["mean"] == pytest.approx(23 / 6) and paired["n"] == 3
    assert "rigid - static: HCM" not in payload["paired"]  # rigid was not run
    one = FeedForwardStudyConfig(seeds=(0,), variants=("static", "decoupled"))
    text, _ = feedforward_report(
        _runs({"static": [1.0], "decoupled": [2.0]}), one, wall_seconds=1.0, device="cpu"
    )
    assert "no intervals" in text and "1 seed(s): no interval" in text


def test_won_back_is_the_share_of_the_harm() -> None:
    runs = _runs({"single-frame": [10.0] * 3, "static": [4.0] * 3, "velocity": [8.0] * 3}).runs
    found = won_back(runs, "velocity")
    assert found is not None
    share, half = found
    assert share == pytest.approx(4 / 6)
    assert half.n == 3 and half.mean == pytest.approx(1.0) and half.low == pytest.approx(1.0)
    assert won_back(runs, "decoupled") is None  # not run
    assert won_back(runs, "velocity", score="mIoU") == found  # the same numbers everywhere
    # per seed: gains 4, 3, 3 of harms 6, 6, 6; gain - harm / 2 = 1, 0, 0
    runs = _runs(
        {
            "single-frame": [10.0, 12.0, 11.0],
            "static": [4.0, 6.0, 5.0],
            "velocity": [8.0, 9.0, 8.0],
        }
    ).runs
    found = won_back(runs, "velocity")
    assert found is not None
    assert found[0] == pytest.approx(10 / 18)
    assert found[1].mean == pytest.approx(1 / 3) and found[1].low < 0 < found[1].high
    # only the seeds with all three variants count
    partial = [r for r in runs if not (r.variant == "velocity" and r.seed == 2)]
    found = won_back(partial, "velocity")
    assert found is not None and found[1].n == 2
    assert found[0] == pytest.approx(7 / 12) and found[1].mean == pytest.approx(0.5)
    assert won_back([r for r in runs if r.variant != "single-frame"], "velocity") is None
    assert won_back([r for r in runs if r.variant != "static"], "velocity") is None


@pytest.mark.parametrize("single_frame", [4.0, 3.0])
def test_won_back_without_harm_is_nan(single_frame: float) -> None:
    runs = _runs(
        {"single-frame": [single_frame] * 3, "static": [4.0] * 3, "velocity": [8.0] * 3}
    ).runs
    found = won_back(runs, "velocity")
    assert found is not None and math.isnan(found[0])
    assert found[1].mean == pytest.approx(4 - (single_frame - 4) / 2)


def test_the_report_says_what_each_variant_wins_back() -> None:
    result = _runs(
        {
            "single-frame": [10.0, 10.0, 10.0],
            "static": [4.0, 4.0, 4.0],
            "rigid": [4.0, 5.0, 6.0],
            "decoupled": [5.0, 5.0, 5.0],
            "velocity": [8.0, 8.0, 8.0],
            "true-motion": [10.0, 9.0, 11.0],
        }
    )
    config = FeedForwardStudyConfig(seeds=(0, 1, 2))
    text, payload = feedforward_report(result, config, wall_seconds=1.0, device="cpu")
    lines = [line for line in text.splitlines() if "wins back" in line]
    assert len(lines) == 4
    assert "- velocity wins back 67% of the harm on HCM" in text
    assert "- decoupled wins back 17% of the harm on HCM" in text
    assert "- true motion (oracle) wins back 100% of the harm on HCM" in text
    velocity = next(line for line in lines if line.startswith("- velocity"))
    assert "at least half, the interval excludes 0" in velocity
    decoupled = next(line for line in lines if line.startswith("- decoupled"))
    assert "less than half, the interval excludes 0" in decoupled
    assert payload["won_back"]["velocity"]["share"] == pytest.approx(2 / 3)
    assert payload["won_back"]["velocity"]["at_least_half"]["mean"] == pytest.approx(1.0)
    assert set(payload["won_back"]) == {"true-motion", "decoupled", "velocity", "rigid"}
    # the velocity comparisons are in the paired table
    assert ("velocity", "static") in COMPARISONS and ("velocity", "decoupled") in COMPARISONS
    assert payload["paired"]["velocity - decoupled: HCM"]["mean"] == pytest.approx(3.0)
    assert "| velocity - static | 3 |" in text
    assert "velocity or DeGO's time-conditioned rigid branch?" in text
    # no harm: the reading says so
    flat = _runs({"single-frame": [4.0] * 3, "static": [4.0] * 3, "velocity": [8.0] * 3})
    config = FeedForwardStudyConfig(
        seeds=(0, 1, 2), variants=("single-frame", "static", "velocity")
    )
    text, payload = feedforward_report(flat, config, wall_seconds=1.0, device="cpu")
    assert "there is no harm to win back" in text and "wins back" not in text
    assert math.isnan(payload["won_back"]["velocity"]["share"])


@pytest.mark.slow
def test_quick_runs_the_chosen_variants_and_writes_its_outputs(tmp_path: Path) -> None:
    """The command end to end (two variants: training every variant is tested in-process
    in test_feedforward.py, at a fraction of a subprocess's cost)."""
    out = tmp_path / "out"
    variants = ("static", "true-motion")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    result = subprocess.run(
        [
            *(sys.executable, "-m", "dego", "train", "--quick", "--variants", ",".join(variants)),
            *("--cache", str(tmp_path / "cache"), "--out", str(out)),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=1200,  # a hang: the run takes 45-75 s here, several times that under load
    )
    assert result.returncode == 0, result.stderr[-3000:]
    payload = json.loads((out / "train.json").read_text())
    assert [r["variant"] for r in payload["runs"]] == list(variants)
    assert payload["settings"]["train"]["steps"] == PRESETS["quick"].train.steps
    for variant in variants:
        assert (out / f"heldout_{variant}.png").stat().st_size > 1000
    assert not (out / "heldout_decoupled.png").exists()
    table = (out / "train.md").read_text()
    assert "| true motion (oracle) |" in table and "| static |" in table
    assert "| decoupled |" not in table
    assert "ETA" in result.stderr  # the progress bar
    assert list((tmp_path / "cache").glob("scenes-*/scene-*.npz"))


def test_help_the_docs_and_the_readme_agree(source_tree: Path) -> None:
    from dego.cli import build_parser

    parser = build_parser()
    train = parser._subparsers._group_actions[0].choices["train"]  # type: ignore[union-attr]
    text = " ".join(train.format_help().split())
    assert command.TRAIN_DURATION in text and "--device" in text and "--cache" in text
    page = " ".join((source_tree / "docs" / "feedforward.md").read_text().split())
    assert command.TRAIN_DURATION in page
    flags = ("--quick", "--full", "--seeds", "--variants", "--steps", "--cache", "--out")
    flags += ("--warmup-steps", "--recipe", "--depth", "--frames", "--frame-dt", "--depth-noise")
    for flag in flags:
        assert flag in page and flag in text, flag
    for variant in FEEDFORWARD_VARIANTS:
        assert f"`{variant}`" in page or variant == "true-motion", variant
    readme = (source_tree / "README.md").read_text()
    assert "dego train" in readme and "docs/feedforward.md" in readme


@pytest.mark.slow
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_quick_runs_on_cuda(tmp_path: Path) -> None:
    code = main(
        [
            *("train", "--quick", "--device", "cuda", "--cache", str(tmp_path / "c")),
            *("--out", str(tmp_path / "out"), "--no-pictures"),
        ]
    )
    assert code == 0
    payload = json.loads((tmp_path / "out" / "train.json").read_text())
    assert payload["settings"]["device"] == "cuda"
    assert all(r["scores"]["IoU"] is not None for r in payload["runs"])


@pytest.mark.parametrize(
    ("recorded", "frame_dt"),
    [("feedforward-train.json", 0.5), ("feedforward-train-0.2s.json", 0.2)],
)
def test_the_docs_tables_are_the_recorded_run(
    source_tree: Path, recorded: str, frame_dt: float
) -> None:
    """docs/feedforward.md's tables are the reports of the runs recorded beside it: the
    study at the defaults and the 0.2 s contrast."""
    import math

    from dego.demo.feedforward import DataConfig, TrainConfig

    payload = json.loads((source_tree / "docs" / "results" / recorded).read_text())

    def nan(value: float | None) -> float:
        return math.nan if value is None else value

    runs = [
        StudyRun(
            **{
                **r,
                "scores": {k: nan(v) for k, v in r["scores"].items()},
                "per_articulated_agent": nan(r["per_articulated_agent"]),
            }
        )
        for r in payload["runs"]
    ]
    settings = payload["settings"]
    data = {**settings["data"], "image_size": tuple(settings["data"]["image_size"])}
    config = FeedForwardStudyConfig(
        seeds=tuple(settings["seeds"]),
        variants=tuple(settings["variants"]),
        data=DataConfig(**data),
        train=TrainConfig(**settings["train"]),
    )
    assert config.train == PRESETS["cpu"].train  # the defaults were what ran
    assert config.seeds == PRESETS["full"].seeds and config.data.frame_dt == frame_dt
    assert config.data == dataclasses.replace(PRESETS["cpu"].data, frame_dt=frame_dt)
    text, _ = feedforward_report(
        FeedForwardRuns(runs, {}, None, settings["data_seconds"], settings["warmup_seconds"]),
        config,
        wall_seconds=settings["wall_seconds"],
        device=settings["device"],
    )
    page = (source_tree / "docs" / "feedforward.md").read_text()
    tables = [line for line in text.splitlines() if line.startswith("|")]
    assert len(tables) >= 2 + len(config.variants)
    for line in tables:
        assert line in page, line
