"""`dego study`: statistics (ROC-AUC, t-intervals, pairing), configuration and the quick run."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego.cli import main
from dego.demo.study import (
    METRICS,
    QUICK_STUDY,
    STUDY_VARIANTS,
    StudyConfig,
    StudyRun,
    mean_interval,
    paired_differences,
    roc_auc,
)

# -- statistics --------------------------------------------------------------------------


def test_roc_auc_analytic_cases() -> None:
    assert roc_auc(torch.tensor([0.9, 0.8]), torch.tensor([0.1, 0.2, 0.3])) == 1.0
    assert roc_auc(torch.tensor([0.1]), torch.tensor([0.5, 0.6])) == 0.0
    assert roc_auc(torch.full((3,), 0.5), torch.full((4,), 0.5)) == 0.5
    assert roc_auc(torch.tensor([1.0, 0.0]), torch.tensor([0.5])) == 0.5
    assert math.isnan(roc_auc(torch.zeros(0), torch.ones(2)))
    assert math.isnan(roc_auc(torch.ones(2), torch.zeros(0)))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.integers(0, 5), min_size=1, max_size=30),
    st.lists(st.integers(0, 5), min_size=1, max_size=30),
)
def test_roc_auc_matches_brute_force_and_is_antisymmetric(a: list[int], b: list[int]) -> None:
    positive, negative = torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32)
    brute = sum((x > y) + 0.5 * (x == y) for x in a for y in b) / (len(a) * len(b))
    assert roc_auc(positive, negative) == pytest.approx(brute)
    assert roc_auc(positive, negative) + roc_auc(negative, positive) == pytest.approx(1.0)


def test_intervals_from_fewer_than_three_seeds_are_flagged_not_printed() -> None:
    from dego.demo.study import MIN_INTERVAL_SEEDS

    assert MIN_INTERVAL_SEEDS == 3
    two = mean_interval([0.4, 1.0])  # an AUC-like quantity: the t-interval leaves [0, 1]
    assert two.n == 2 and two.low < 0 and two.high > 1  # the JSON keeps it as it is
    assert str(two) == "0.70 [n/a (2 seeds)]"
    far = mean_interval([5.0, 5.1])  # excludes 0, but 2 seeds resolve no sign
    assert far.low > 0 and not far.excludes_zero()
    assert mean_interval([5.0, 5.1, 4.9]).excludes_zero()


def made_up_runs(seeds: Iterable[int], mask_step: float = 0.0) -> list[StudyRun]:
    """``static`` and ``decoupled`` runs at budget 10: every score 1, articulated t=±1
    5 + seed and 9 + seed, every mask statistic 0.5 + mask_step * seed."""
    from dego.demo.study import MASK_METRICS

    return [
        StudyRun(
            seed,
            10,
            variant,
            dict.fromkeys(METRICS, 1.0) | {"articulated t=±1": value + seed},
            dict.fromkeys(MASK_METRICS, 0.5 + mask_step * seed),
            3.0,
            1.0,
        )
        for seed in seeds
        for variant, value in (("static", 5.0), ("decoupled", 9.0))
    ]


@pytest.mark.parametrize("seeds", [(0, 1), (0, 1, 2)])
def test_report_flags_too_few_seeds(seeds: tuple[int, ...]) -> None:
    from dego.demo.study import study_report

    runs = made_up_runs(seeds, mask_step=0.1)
    text, payload = study_report(runs, StudyConfig(seeds=seeds, budgets=(10,)))
    flagged = len(seeds) < 3
    assert ("no interval is given (`n/a`)" in text) == flagged
    assert ("[n/a (2 seeds)]" in text) == flagged
    assert ("2 seeds only: no interval" in text) == flagged
    assert (" *" in text) != flagged  # a resolved sign needs 3 seeds
    interval = payload["paired"]["decoupled - static @ 10: articulated t=±1"]
    assert interval["n"] == len(seeds) and interval["low"] == pytest.approx(4.0)


def test_study_help_gives_the_device_and_the_duration_the_docs_give(source_tree: Path) -> None:
    from dego.cli import build_parser
    from dego.demo.study.command import STUDY_DURATION

    parser = build_parser()
    study = parser._subparsers._group_actions[0].choices["study"]  # type: ignore[union-attr]
    text = " ".join(study.format_help().split())
    assert "--device" in text and STUDY_DURATION in text
    page = " ".join((source_tree / "docs" / "study.md").read_text().split())
    assert STUDY_DURATION in page and "--device" in page
    assert parser.parse_args(["study", "--device", "cpu"]).device == "cpu"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_study_runs_on_cuda(tmp_path: Path) -> None:
    argv = ["study", "--device", "cuda", "--seeds", "0", "--budgets", "300", "--frames", "2"]
    argv += ["--iterations", "3", "--variants", "static,decoupled", "--no-pictures"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    payload = json.loads((tmp_path / "study.json").read_text())
    assert {r["variant"] for r in payload["runs"]} == {"static", "decoupled"}


def test_mean_interval_known_values() -> None:
    interval = mean_interval([1.0, 2.0, 3.0])
    half = 4.303 / math.sqrt(3)  # t(0.975, 2 dof) * sd 1 / sqrt(3)
    assert (interval.mean, interval.n) == (2.0, 3)
    assert interval.low == pytest.approx(2 - half) and interval.high == pytest.approx(2 + half)
    assert not interval.excludes_zero()
    assert mean_interval([5.0, 5.1, 4.9, 5.0]).excludes_zero()
    assert mean_interval([-5.0, -5.1, -4.9]).excludes_zero()
    single = mean_interval([1.0, math.nan])  # NaNs are dropped
    assert single.n == 1 and single.mean == 1.0 and not single.excludes_zero()
    assert str(single) == "1.00"
    assert math.isnan(mean_interval([]).mean) and str(mean_interval([])) == "nan"
    assert str(interval) == f"2.00 [{2 - half:.2f}, {2 + half:.2f}]"


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-100, 100), min_size=2, max_size=40), st.floats(-50, 50))
def test_mean_interval_contains_the_mean_and_shifts_with_the_data(
    values: list[float], shift: float
) -> None:
    interval = mean_interval(values)
    assert interval.low <= interval.mean <= interval.high
    shifted = mean_interval([v + shift for v in values])
    assert shifted.mean == pytest.approx(interval.mean + shift, abs=1e-6)
    assert shifted.high - shifted.low == pytest.approx(interval.high - interval.low, abs=1e-6)


def run(seed: int, budget: int, variant: str, articulated: float) -> StudyRun:
    scores = dict.fromkeys(METRICS, 0.0) | {"articulated t=±1": articulated}
    return StudyRun(seed, budget, variant, scores, {}, 0.0, 1.0)


def test_paired_differences_pair_by_seed_and_budget() -> None:
    runs = [
        run(0, 10, "rigid", 10.0),
        run(0, 10, "decoupled", 13.0),
        run(1, 10, "rigid", 50.0),
        run(1, 10, "decoupled", 52.0),
        run(0, 20, "rigid", 1.0),
        run(0, 20, "decoupled", 0.0),
        run(2, 20, "decoupled", 99.0),  # no rigid partner: left out
    ]
    paired = paired_differences(runs, "articulated t=±1", "decoupled", "rigid")
    assert paired[10].mean == pytest.approx(2.5) and paired[10].n == 2
    assert paired[20].mean == pytest.approx(-1.0) and paired[20].n == 1


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("seeds", ()),
        ("seeds", (-1,)),
        ("budgets", (0,)),
        ("frames", 1),
        ("iterations", -1),
        ("variants", ("flow",)),
        ("mask_prior", -0.1),
        ("mask_prior", float("nan")),
    ],
)
def test_study_config_rejects_bad_values(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        StudyConfig(**{field: value})  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--seeds", "a-b"], "--seeds"),
        (["--budgets", "0"], "--budgets"),
        (["--frames", "1"], "--frames"),
        (["--mask-prior", "-1"], "--mask-prior"),
        (["--variants", "static,flow"], "--variants"),
    ],
)
def test_bad_study_arguments_exit_with_a_message(
    arguments: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["study", *arguments])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


# -- the quick study, end to end -------------------------------------------------------------


# The quick study's variants less the two motion baselines that `dego demo --quick` fits in
# tests/demo/test_demo.py (a third less time; every other variant's path stays end to end).
QUICK_TEST_VARIANTS = tuple(
    v for v in STUDY_VARIANTS if v not in ("free-offsets", "free-velocities")
)
QUICK_TEST_ITERATIONS = 6


@pytest.fixture(scope="module")
def quick_study(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("study")
    # --quick at 6 iterations a fit (--quick's own 20 change no line of the report's
    # layout): 27 s on one idle core instead of 60-85 s
    command = ["study", "--quick", "--variants", ",".join(QUICK_TEST_VARIANTS)]
    command += ["--iterations", str(QUICK_TEST_ITERATIONS)]
    result = subprocess.run(
        [sys.executable, "-m", "dego", *command, "--device", "cpu", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=1200,  # a hang: the run takes 25-40 s here, several times that under load
    )
    assert result.returncode == 0, result.stderr
    return out, result.stdout


@pytest.mark.slow
def test_quick_study_writes_the_report(quick_study: tuple[Path, str]) -> None:
    pytest.importorskip("matplotlib")
    out, stdout = quick_study
    assert {p.name for p in out.iterdir()} == {"study.md", "study.json", "study.png"}
    text = (out / "study.md").read_text()
    for heading in ("## 300 Gaussians", "## Paired differences", "## Reading"):
        assert heading in text
    for pair in ("decoupled - static", "decoupled - rigid", "true motion (oracle) - static"):
        assert f"| {pair} | 300 | 2 |" in text, pair
    assert "static - single-frame" in text
    assert "decoupled - static on articulated t=±1" in text
    assert "the ground-truth motion (oracle) gains" in text
    assert text in stdout  # the report is also printed
    # the progress counter reaches its total: one line per run, lifted-labels included
    runs = len(QUICK_STUDY.seeds) * len(QUICK_STUDY.budgets) * len(QUICK_TEST_VARIANTS)
    fits = runs - len(QUICK_STUDY.seeds) * len(QUICK_STUDY.budgets)
    assert f"study: {runs} runs, {fits} of them fits" in stdout
    counters = [line.split()[0] for line in stdout.splitlines() if line.startswith("[")]
    assert counters == [f"[{i}/{runs}" for i in range(1, runs + 1)]
    assert "lifted-labels (no fit): articulated t=±1" in stdout


@pytest.mark.slow
def test_quick_study_json_holds_every_run(quick_study: tuple[Path, str]) -> None:
    out, _ = quick_study
    payload = json.loads((out / "study.json").read_text())
    assert payload["units"]["scores"] == "percent"
    runs = payload["runs"]
    expected = len(QUICK_STUDY.seeds) * len(QUICK_STUDY.budgets) * len(QUICK_TEST_VARIANTS)
    assert len(runs) == expected
    assert {r["variant"] for r in runs} == set(QUICK_TEST_VARIANTS)
    for r in runs:
        assert set(r["scores"]) == set(METRICS)
        finite = [v for v in r["scores"].values() if v is not None]
        assert all(0 <= v <= 100 for v in finite)
        assert r["scores"]["mIoU t=0"] is not None and r["scores"]["mIoU t=0"] > 0
        if r["variant"] == "lifted-labels":
            assert r["mask"]["mask static"] is None and r["seconds"] == 0.0  # no fit
        elif not r["variant"].startswith("decoupled") and r["variant"] != "velocity":
            assert r["mask"]["mask static"] == 0.0  # no learned mask: m = 0
        else:
            auc = r["mask"]["mask AUC"]
            assert auc is None or 0 <= auc <= 1
    assert set(payload["summary"]) == {str(b) for b in QUICK_STUDY.budgets}
    assert "decoupled - rigid @ 300: articulated t=±1" in payload["paired"]
    assert "decoupled - static @ 300: HCM t=0" in payload["paired"]


def test_default_study_leaves_out_the_mask_prior_variant() -> None:
    from dego.demo.study import DEFAULT_STUDY_VARIANTS

    assert "decoupled+prior" not in StudyConfig().variants
    assert StudyConfig().variants == DEFAULT_STUDY_VARIANTS
    assert "velocity" not in StudyConfig().variants  # ours, on request
    assert set(DEFAULT_STUDY_VARIANTS) | {"decoupled+prior", "velocity"} == set(STUDY_VARIANTS)
    assert QUICK_STUDY.variants == STUDY_VARIANTS  # the tests run every variant


def test_paired_report_marks_resolved_signs() -> None:
    from dego.demo.study import study_report

    runs = made_up_runs(range(3))
    text, payload = study_report(runs, StudyConfig(seeds=(0, 1, 2), budgets=(10,)))
    line = next(x for x in text.splitlines() if x.startswith("| decoupled - static | 10 |"))
    assert "4.00 [4.00, 4.00] *" in line
    assert payload["paired"]["decoupled - static @ 10: articulated t=±1"]["mean"] == 4.0


def test_the_quick_plot_keeps_its_titles_labels_and_legends_inside_the_figure() -> None:
    """Issue 51: ``dego study --quick``'s right-hand title ("..., no interval (needs
    3+)", one line) ran past the figure's right edge and was cut off in study.png (saved
    at the figure's size, no tight bounding box)."""
    pytest.importorskip("matplotlib")
    from dego.demo.study import MASK_METRICS, study_figure

    runs = [
        StudyRun(
            seed,
            budget,
            variant,
            dict.fromkeys(METRICS, 0.0) | {"articulated t=±1": 10.0 + seed + k},
            dict.fromkeys(MASK_METRICS, 0.5),
            0.0,
            1.0,
        )
        for seed in QUICK_STUDY.seeds
        for budget in QUICK_STUDY.budgets
        for k, variant in enumerate(QUICK_STUDY.variants)
    ]
    figure = study_figure(runs)
    figure.canvas.draw()
    page = figure.bbox
    assert "no interval" in figure.axes[1].get_title()  # the quick study's long title
    for axis in figure.axes:
        legend = axis.get_legend()
        for item in (axis.title, axis.xaxis.label, axis.yaxis.label, legend):
            if item is None or (hasattr(item, "get_text") and not item.get_text()):
                continue
            box = item.get_window_extent()
            inside = page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0
            assert inside and box.y1 <= page.y1, (item, box, page)


@pytest.mark.parametrize("seeds", [2, 3])
def test_the_plot_draws_intervals_only_where_the_report_gives_them(seeds: int) -> None:
    """Issue 41 (5): with 2 seeds (``--quick``) the report prints n/a; the plot then draws
    no error bars and its title says why, instead of "95% CI" over zero-width bars."""
    pytest.importorskip("matplotlib")
    from dego.demo.study import MASK_METRICS, study_figure

    runs = [
        StudyRun(
            seed,
            300,
            variant,
            dict.fromkeys(METRICS, 0.0) | {"articulated t=±1": 10.0 + seed * (1 + k)},
            dict.fromkeys(MASK_METRICS, 0.5),
            0.0,
            1.0,
        )
        for seed in range(seeds)
        for k, variant in enumerate(("static", "rigid", "decoupled"))
    ]
    from matplotlib.container import BarContainer

    left, right = study_figure(runs).axes
    bars = [c for axis in (left, right) for c in axis.containers if isinstance(c, BarContainer)]
    error_bars = [c.errorbar for c in bars]
    assert len(bars) == 3 + 2  # the variants, then the gains of rigid and decoupled
    title = right.get_title()
    if seeds < 3:
        assert all(bar is None for bar in error_bars)
        assert "95% CI" not in title and "2 seed(s), no interval (needs 3+)" in title
    else:
        assert all(bar is not None for bar in error_bars) and "95% CI" in title
