"""``dego study``: when does decoupling pay off? Variants x seeds x Gaussian budgets.

For every seed a synthetic clip is rendered; for every total Gaussian budget each variant
(``static``, ``rigid``, ``decoupled``, ``decoupled`` with the optional mask prior, and the
reference rows ``single-frame``, ``free-offsets``, ``free-velocities`` and the
ground-truth ``true-motion`` oracle) is fitted from the pseudo labels and scored at every
frame (:mod:`dego.demo`). The report gives per-variant means with 95% confidence intervals
over seeds, paired differences (e.g. decoupled - static on moving agents at the
non-reference frames and on HCM at the reference frame), and how well the learned
rigidity mask separates articulated agents from vehicles.

Modules: ``runner`` (variants, scores, :class:`StudyConfig`, :func:`run_study`,
:func:`summarise`), ``report`` (:func:`study_report`, :func:`write_study`), ``picture``
(:func:`study_figure`) and ``command`` (the ``dego study`` command line). The statistics
(:class:`Interval`, :func:`mean_interval`, :func:`paired_differences`, :class:`StudyRun`)
live in :mod:`dego.demo.stats`, shared with ``dego train``.
"""

from dego.demo.stats import (
    MIN_INTERVAL_SEEDS,
    Interval,
    StudyRun,
    check_distinct,
    check_seeds,
    mean_interval,
    paired_differences,
)
from dego.demo.study.picture import PICTURED_GAINS, study_figure, study_picture, study_png
from dego.demo.study.report import COMPARISONS, PAIRED_METRICS, study_report, write_study
from dego.demo.study.runner import (
    DEFAULT_STUDY_VARIANTS,
    HEADLINE,
    MASK_METRICS,
    METRICS,
    QUICK_STUDY,
    STUDY_VARIANTS,
    StudyConfig,
    mask_statistics,
    roc_auc,
    run_study,
    summarise,
)

__all__ = [
    "COMPARISONS",
    "DEFAULT_STUDY_VARIANTS",
    "HEADLINE",
    "MASK_METRICS",
    "METRICS",
    "MIN_INTERVAL_SEEDS",
    "PAIRED_METRICS",
    "PICTURED_GAINS",
    "QUICK_STUDY",
    "STUDY_VARIANTS",
    "Interval",
    "StudyConfig",
    "StudyRun",
    "check_distinct",
    "check_seeds",
    "mask_statistics",
    "mean_interval",
    "paired_differences",
    "roc_auc",
    "run_study",
    "study_figure",
    "study_picture",
    "study_png",
    "study_report",
    "summarise",
    "write_study",
]
