"""The Occ3D-nuScenes scoring pipeline behind ``dego eval``: readers (ground truth,
predictions, ray origins), a streaming loop over samples (one process, spawned workers or
torchrun ranks through torch.distributed), progress, and reports.

    report = dego.evaluate("data/occ3d-nus", "preds", infos="nuscenes_infos_val.pkl")
    print(report.tables())            # percent, 2 decimals
    Path("report.json").write_text(report.to_json())  # percent, "units": "percent"
"""

from dego.evaluation.errors import EvaluationSetupError, EvaluationWorkerError, SampleFailure
from dego.evaluation.origins import DirectoryOrigins, OriginSource
from dego.evaluation.predictions import PREDICTION_KEYS, find_prediction, load_prediction
from dego.evaluation.progress import Progress
from dego.evaluation.report import EvaluationReport
from dego.evaluation.run import evaluate

__all__ = [
    "PREDICTION_KEYS",
    "DirectoryOrigins",
    "EvaluationReport",
    "EvaluationSetupError",
    "EvaluationWorkerError",
    "OriginSource",
    "Progress",
    "SampleFailure",
    "evaluate",
    "find_prediction",
    "load_prediction",
]
