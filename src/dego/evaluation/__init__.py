"""The scoring pipeline behind ``dego eval``: one declarative spec per benchmark
(:data:`BENCHMARKS`: Occ3D-nuScenes, Occ3D-Waymo, SurroundOcc in two conventions,
OpenOccupancy, OpenOcc v2, NuPlan-Occ), readers of each ground-truth layout and of the
predictions, ray origins, a streaming loop over samples (one process, spawned workers or
torchrun ranks through torch.distributed), progress, and reports that name every rule;
small synthetic trees in every layout (:func:`write_benchmark_tree`).

    report = dego.evaluate("data/occ3d-nus", "preds", infos="nuscenes_infos_val.pkl")
    report = dego.evaluate("voxel04/validation", "preds", benchmark="occ3d-waymo")
    print(report.tables())            # percent, 2 decimals
    Path("report.json").write_text(report.to_json())  # percent, "units": "percent"
"""

from dego.evaluation.benchmarks import (
    BENCHMARKS,
    OCC3D_TO_OPENOCC,
    Benchmark,
    RayProtocol,
    VoxelProtocol,
    get_benchmark,
)
from dego.evaluation.errors import EvaluationSetupError, EvaluationWorkerError, SampleFailure
from dego.evaluation.layouts import GroundTruth
from dego.evaluation.openocc import occ3d_to_openocc, write_openocc_submission
from dego.evaluation.origins import DirectoryOrigins, OriginSource
from dego.evaluation.predictions import (
    PREDICTION_KEYS,
    find_prediction,
    load_prediction,
    read_prediction,
)
from dego.evaluation.progress import Progress
from dego.evaluation.report import EvaluationReport
from dego.evaluation.run import evaluate
from dego.evaluation.trees import BenchmarkTree, write_benchmark_tree

__all__ = [
    "BENCHMARKS",
    "OCC3D_TO_OPENOCC",
    "PREDICTION_KEYS",
    "Benchmark",
    "BenchmarkTree",
    "DirectoryOrigins",
    "EvaluationReport",
    "EvaluationSetupError",
    "EvaluationWorkerError",
    "GroundTruth",
    "OriginSource",
    "Progress",
    "RayProtocol",
    "SampleFailure",
    "VoxelProtocol",
    "evaluate",
    "find_prediction",
    "get_benchmark",
    "load_prediction",
    "occ3d_to_openocc",
    "read_prediction",
    "write_benchmark_tree",
    "write_openocc_submission",
]
