"""The voxelizer's options, written once: the ``Literal`` aliases and :class:`VoxelizerConfig`.

:class:`VoxelizerConfig` holds every option's annotation, default and validation;
:func:`dego.voxelizer.voxelize` builds it by name from its keywords and
:class:`dego.voxelizer.GaussianVoxelizer` from ``config`` and ``**overrides``
(:class:`VoxelizerOptions`: the same options as a ``TypedDict``, for the signature).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal, TypedDict

Mode = Literal["additive", "probabilistic"]
Neighborhood = Literal["ellipsoid", "cube", "scale_cube"]
FeatureWeight = Literal["kernel", "opacity_kernel"]

TINY_WEIGHT = 1e-30  # default empty_threshold


@dataclasses.dataclass(frozen=True)
class VoxelizerConfig:
    """Settings shared by :func:`voxelize` and :class:`GaussianVoxelizer` (each option is
    documented in :func:`voxelize`); a bad value raises ``ValueError`` naming the option."""

    mode: Mode = "additive"
    neighborhood: Neighborhood = "ellipsoid"
    cutoff_sigma: float = 3.0
    nbh: int | None = None
    chunk_size: int = 1 << 21
    scale_multiplier: float | int | None = None
    feature_weight: FeatureWeight | None = None
    opacity_in_density: bool = True
    empty_value: float | int = 0.0
    empty_threshold: float = TINY_WEIGHT

    def __post_init__(self) -> None:
        if self.mode not in ("additive", "probabilistic"):
            raise ValueError(f"mode: expected 'additive' or 'probabilistic', got {self.mode!r}")
        if self.neighborhood not in ("ellipsoid", "cube", "scale_cube"):
            raise ValueError(
                "neighborhood: expected 'ellipsoid', 'cube' or 'scale_cube', got "
                f"{self.neighborhood!r}"
            )
        self._check_gaussianformer_options()
        k = self.cutoff_sigma
        if isinstance(k, bool) or not isinstance(k, int | float) or not k > 0:  # NaN fails
            raise ValueError(
                f"cutoff_sigma: expected a positive number (inf: the whole grid), got {k!r}"
            )
        if self.neighborhood == "cube":
            if self.nbh is None:
                raise ValueError("nbh: required with neighborhood='cube' (official: 4 or 5)")
            if not isinstance(self.nbh, int) or isinstance(self.nbh, bool) or self.nbh < 0:
                raise ValueError(f"nbh: expected an int >= 0, got {self.nbh!r}")
        if (
            isinstance(self.chunk_size, bool)
            or not isinstance(self.chunk_size, int)
            or self.chunk_size < 1
        ):
            raise ValueError(f"chunk_size: expected a positive int, got {self.chunk_size!r}")

    def _check_gaussianformer_options(self) -> None:
        k = self.scale_multiplier
        if self.neighborhood == "scale_cube":
            if k is None:
                raise ValueError(
                    "scale_multiplier: required with neighborhood='scale_cube' "
                    "(GaussianFormer: 3, GaussianFormer-2: 4)"
                )
            if isinstance(k, bool) or not isinstance(k, int | float) or not k > 0:  # NaN fails
                raise ValueError(
                    f"scale_multiplier: expected a positive number (inf: the whole grid), got {k!r}"
                )
        elif k is not None:
            raise ValueError(
                f"scale_multiplier: only used with neighborhood='scale_cube', got {k!r} with "
                f"neighborhood={self.neighborhood!r}"
            )
        if self.feature_weight not in (None, "kernel", "opacity_kernel"):
            raise ValueError(
                "feature_weight: expected None, 'kernel' or 'opacity_kernel', got "
                f"{self.feature_weight!r}"
            )
        if not isinstance(self.opacity_in_density, bool):
            raise ValueError(
                f"opacity_in_density: expected True or False, got {self.opacity_in_density!r}"
            )
        value = self.empty_value
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise ValueError(f"empty_value: expected a finite number, got {value!r}")
        t = self.empty_threshold
        if isinstance(t, bool) or not isinstance(t, int | float) or not 0 <= t < math.inf:
            raise ValueError(f"empty_threshold: expected a finite number >= 0, got {t!r}")

    @property
    def opacity_weights_features(self) -> bool:
        """Whether the feature weight includes the opacity: ``feature_weight`` if given,
        else ``False`` in additive mode (``sum g f``) and ``True`` in probabilistic mode
        (mixture weight ``o N``)."""
        if self.feature_weight is None:
            return self.mode == "probabilistic"
        return self.feature_weight == "opacity_kernel"


class VoxelizerOptions(TypedDict, total=False):
    """The fields of :class:`VoxelizerConfig` as keyword overrides of
    :class:`GaussianVoxelizer` (a test keeps the two identical)."""

    mode: Mode
    neighborhood: Neighborhood
    cutoff_sigma: float
    nbh: int | None
    chunk_size: int
    scale_multiplier: float | int | None
    feature_weight: FeatureWeight | None
    opacity_in_density: bool
    empty_value: float | int
    empty_threshold: float


__all__ = ["FeatureWeight", "Mode", "Neighborhood", "VoxelizerConfig", "VoxelizerOptions"]
