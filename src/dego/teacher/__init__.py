"""Factorized spatio-temporal teacher and feature distillation (DeGO section 4.2)."""

from dego.teacher.cache import TeacherFeatureCache
from dego.teacher.factorized import (
    AttentionBlock,
    FactorizedSpatioTemporalTeacher,
    TeacherOutput,
    rotary_2d,
)
from dego.teacher.features import FactorizedTeacherFeatures
from dego.teacher.loss import DistillationLoss, cosine_distance_map, distillation_loss
from dego.teacher.student import StudentProjector

__all__ = [
    "AttentionBlock",
    "DistillationLoss",
    "FactorizedSpatioTemporalTeacher",
    "FactorizedTeacherFeatures",
    "StudentProjector",
    "TeacherFeatureCache",
    "TeacherOutput",
    "cosine_distance_map",
    "distillation_loss",
    "rotary_2d",
]
