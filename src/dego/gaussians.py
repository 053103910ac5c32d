"""3D Gaussians: the :class:`GaussianSet` container and quaternion/covariance helpers.

Conventions (see ``docs/conventions.md``): quaternions are ``(w, x, y, z)``, need not
be unit (they are normalised inside, ``q`` and ``-q`` are the same rotation), scales
are per-axis standard deviations in metres, and the covariance is
``Sigma = R diag(s^2) R^T``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, ClassVar

import numpy as np
import torch
import torch.utils._pytree as pytree
from jaxtyping import Bool, Float, Int, Integer
from torch import Tensor

from dego import _serialization
from dego._geometry import (
    QUATERNION_EPS,
    conjugate_quaternions,
    quaternion_product,
    rotation_matrices,
    scaled_rotation_gram,
    unit_quaternions,
)
from dego._policy import (
    HALF_DTYPES,
    autocast_enabled,
    check_dtype,
    finite_check,
    float32_under_autocast,
    gaussian_value_checks,
    run_checks,
    scales_check,
)
from dego._typing import typechecked

try:
    from torch.compiler import is_compiling as _is_compiling
except ImportError:  # torch < 2.3
    from torch._dynamo import is_compiling as _is_compiling

# The public helpers check shapes; GaussianSet (validated once at construction) and other
# internal callers use the private versions above so that checks are not paid per call.


def _check_positive_scales(scales: Tensor) -> None:
    """``ValueError`` naming ``scales`` unless every value is > 0 (NaN fails too)."""
    needed_for = "; precisions need 1/s^2 of positive standard deviations"
    run_checks([scales_check("", scales, needed_for=needed_for)])


@typechecked
def normalize_quaternions(
    quats: Float[Tensor, "*batch 4"], eps: float = QUATERNION_EPS
) -> Float[Tensor, "*batch 4"]:
    """Scale quaternions ``(*, 4)`` (wxyz) to unit norm: ``q / max(|q|, eps)``.

    Norms below ``eps`` are clamped, so a zero quaternion gives zeros (finite values and
    gradients, never ``0 / 0``). The norm is taken after dividing by the largest
    ``|q_k|``, so huge quaternions (``|q| > 1.8e19`` in float32) do not overflow to 0.
    """
    return unit_quaternions(quats, eps)


@typechecked
def quaternions_to_rotation_matrices(
    quats: Float[Tensor, "*batch 4"],
) -> Float[Tensor, "*batch 3 3"]:
    """Rotation matrices ``(*, 3, 3)`` from (possibly unnormalised) wxyz quaternions ``(*, 4)``.

    The result is quadratic in the unit quaternion, so ``q``, ``-q`` and ``lambda * q``
    (``lambda != 0``) give the same matrix. A zero quaternion encodes no rotation; it
    gives the identity (finite, through the ``eps`` clamp of :func:`normalize_quaternions`);
    :meth:`GaussianSet.check_values` and :func:`dego.voxelize` reject it.
    """
    return rotation_matrices(quats)


@typechecked
def build_covariances(
    quats: Float[Tensor, "*batch 4"], scales: Float[Tensor, "*batch 3"]
) -> Float[Tensor, "*batch 3 3"]:
    """Covariances ``R diag(s^2) R^T`` ``(*, 3, 3)`` from quats ``(*, 4)``, scales ``(*, 3)``.

    Raises:
        TypeError: naming ``scales`` when its dtype differs from ``quats``' (nothing is
            promoted silently).
    """
    check_dtype("scales", scales, quats.dtype, "quats")
    return scaled_rotation_gram(quats, scales)


@typechecked
def build_precisions(
    quats: Float[Tensor, "*batch 4"], scales: Float[Tensor, "*batch 3"]
) -> Float[Tensor, "*batch 3 3"]:
    """Inverse covariances ``R diag(1/s^2) R^T`` ``(*, 3, 3)``, computed in closed form.

    No matrix inversion: accurate and cheap even for very anisotropic Gaussians.

    Raises:
        TypeError: naming ``scales`` when its dtype differs from ``quats``'.
        ValueError: naming ``scales`` when a scale is <= 0 or NaN (``1/s^2`` would be
            infinite or NaN).
    """
    check_dtype("scales", scales, quats.dtype, "quats")
    _check_positive_scales(scales)
    return scaled_rotation_gram(quats, scales.reciprocal())


@typechecked
def quaternion_multiply(
    a: Float[Tensor, "*abatch 4"], b: Float[Tensor, "*bbatch 4"]
) -> Float[Tensor, "*batch 4"]:
    """Hamilton product ``a (x) b`` of wxyz quaternions ``(..., 4)`` (broadcasting)."""
    return quaternion_product(a, b)


@typechecked
def rotation_matrices_to_quaternions(
    rotations: Float[Tensor, "*batch 3 3"],
) -> Float[Tensor, "*batch 4"]:
    """Unit wxyz quaternions ``(*, 4)`` with ``w >= 0`` of rotation matrices ``(*, 3, 3)``.

    Each quaternion is read off the largest of ``1 + trace``, ``1 + 2 R_ii - trace`` (the
    squared components times 4), so the division never approaches zero.
    """
    r = rotations
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    candidates = torch.stack(
        [
            torch.stack(
                [
                    1 + trace,
                    r[..., 2, 1] - r[..., 1, 2],
                    r[..., 0, 2] - r[..., 2, 0],
                    r[..., 1, 0] - r[..., 0, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    r[..., 2, 1] - r[..., 1, 2],
                    1 + 2 * r[..., 0, 0] - trace,
                    r[..., 0, 1] + r[..., 1, 0],
                    r[..., 0, 2] + r[..., 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    r[..., 0, 2] - r[..., 2, 0],
                    r[..., 0, 1] + r[..., 1, 0],
                    1 + 2 * r[..., 1, 1] - trace,
                    r[..., 1, 2] + r[..., 2, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    r[..., 1, 0] - r[..., 0, 1],
                    r[..., 0, 2] + r[..., 2, 0],
                    r[..., 1, 2] + r[..., 2, 1],
                    1 + 2 * r[..., 2, 2] - trace,
                ],
                -1,
            ),
        ],
        -2,
    )  # (*, 4, 4): row k is 4 q_k q
    best = candidates.diagonal(dim1=-2, dim2=-1).argmax(-1)  # the largest 4 q_k^2
    picked = torch.take_along_dim(candidates, best[..., None, None], dim=-2).squeeze(-2)
    quats = unit_quaternions(picked)
    return torch.where(quats[..., :1] < 0, -quats, quats)


# ----------------------------------------------------------------------------------------
# GaussianSet
# ----------------------------------------------------------------------------------------

# Options of GaussianSet.from_tensors / to_tensors (see their docstrings).
_QUAT_ORDERS = ("wxyz", "xyzw")
_ROTATIONS = ("R", "R^T")
_SCALE_SPACES = ("std", "variance", "log")
_OPACITY_SPACES = ("prob", "logit")
_OPACITY_SHAPES = ("N", "N1")


def _check_option(name: str, value: object, valid: tuple[str, ...]) -> None:
    if not isinstance(value, str) or value not in valid:
        raise ValueError(f"{name}: expected one of {', '.join(map(repr, valid))}, got {value!r}")


_TRAILING_DIMS: dict[str, int | None] = {
    "means": 3,
    "quats": 4,
    "scales": 3,
    "opacities": None,  # no trailing channel axis: (*batch, N)
    "features": -1,  # any channel count C
}


def _describe_expected(name: str, batch: tuple[int, ...], n: int, channels: int | None) -> str:
    dims = [*map(str, batch), str(n)]
    symbolic = "(*batch, N" + {None: ")", -1: ", C)"}.get(channels, f", {channels})")
    if channels is not None:
        dims.append("C" if channels == -1 else str(channels))
    return f"{name}: expected shape {symbolic} = ({', '.join(dims)})"


def _opacities_hint(name: str, value: Tensor, n: int) -> str:
    """For ``(*batch, N, 1)`` opacities (gsplat's layout): the constructor that takes them."""
    if name != "opacities" or value.ndim < 2 or tuple(value.shape[-2:]) != (n, 1):
        return ""
    return (
        "; GaussianSet.from_tensors(..., opacities=o) takes (*batch, N, 1) opacities (and "
        'logits with opacity_space="logit"), or pass o.squeeze(-1)'
    )


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class GaussianSet(_serialization.DictForm):
    """A (batched) set of N 3D Gaussians; all tensors share batch shape, N, dtype and device.

    Fields:
        means: ``(*batch, N, 3)`` centres in metres.
        quats: ``(*batch, N, 4)`` rotations as wxyz quaternions (any non-zero norm).
        scales: ``(*batch, N, 3)`` per-axis standard deviations in metres (> 0).
        opacities: ``(*batch, N)`` opacities in [0, 1].
        features: optional ``(*batch, N, C)`` per-Gaussian features (semantics, latents).

    Construction validates shapes, dtypes (floating point, identical) and devices and
    raises ``ValueError``/``TypeError`` naming the field. Values are checked on demand
    by :meth:`check_values`. The class is a registered torch pytree, so
    ``torch.utils._pytree.tree_map`` and ``torch.compile`` see its tensors as leaves.
    """

    means: Float[Tensor, "*batch N 3"]
    quats: Float[Tensor, "*batch N 4"]
    scales: Float[Tensor, "*batch N 3"]
    opacities: Float[Tensor, "*batch N"]
    features: Float[Tensor, "*batch N C"] | None = None

    FIELDS: ClassVar[tuple[str, ...]] = tuple(_TRAILING_DIMS)

    def __post_init__(self) -> None:
        for name in self.FIELDS[:4]:
            if getattr(self, name) is None:
                raise TypeError(f"{name}: is required (only features may be None)")
        for name, value in self.items():
            if not isinstance(value, Tensor):
                raise TypeError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
            if not value.is_floating_point():
                raise TypeError(f"{name}: expected a floating-point tensor, got {value.dtype}")
        means = self.means
        if means.ndim < 2 or means.shape[-1] != 3:
            raise ValueError(f"means: expected shape (*batch, N, 3), got {tuple(means.shape)}")
        batch, n = tuple(means.shape[:-2]), means.shape[-2]
        for name, value in self.items():
            channels = _TRAILING_DIMS[name]
            expected_ndim = len(batch) + (1 if channels is None else 2)
            leading = tuple(value.shape[: len(batch) + 1])
            ok = value.ndim == expected_ndim and leading == (*batch, n)
            if ok and channels not in (None, -1):
                ok = value.shape[-1] == channels
            if not ok:
                raise ValueError(
                    f"{_describe_expected(name, batch, n, channels)}, got {tuple(value.shape)}"
                    f"{_opacities_hint(name, value, n)}"
                )
            if value.dtype != means.dtype and not _autocast_features(name, value, means):
                raise TypeError(
                    f"{name}: dtype {value.dtype} differs from means' dtype {means.dtype}; "
                    "all fields must share one floating dtype (features in float16 / "
                    "bfloat16 beside float32 geometry are accepted under torch.autocast)"
                )
            if value.device != means.device:
                raise ValueError(
                    f"{name}: on device {value.device} but means is on {means.device}; "
                    "all fields must be on one device"
                )

    # -- construction helpers --------------------------------------------------------
    @classmethod
    def _unchecked(cls, **fields: Any) -> GaussianSet:
        """Build without validation (pytree unflatten may carry non-tensor leaves)."""
        obj = object.__new__(cls)
        for name in cls.FIELDS:
            object.__setattr__(obj, name, fields.get(name))
        return obj

    @classmethod
    @typechecked
    def from_tensors(
        cls,
        means: Float[Tensor, "*batch N 3"],
        quats: Float[Tensor, "*batch N 4"],
        scales: Float[Tensor, "*batch N 3"],
        opacities: Float[Tensor, "*batch N"] | Float[Tensor, "*batch N 1"],
        features: Float[Tensor, "*batch N C"] | None = None,
        *,
        quat_order: str = "wxyz",
        rotation: str = "R",
        scale_space: str = "std",
        opacity_space: str = "prob",
    ) -> GaussianSet:
        """A validated set from tensors in another code base's conventions (gsplat, 3DGS,
        GaussianFormer), converted to dego's.

        Args:
            means: ``(*batch, N, 3)`` centres, or unbatched ``(N, 3)``.
            quats: ``(*batch, N, 4)`` quaternions in ``quat_order``.
            scales: ``(*batch, N, 3)`` scales in ``scale_space``.
            opacities: ``(*batch, N)`` or ``(*batch, N, 1)`` opacities in ``opacity_space``.
            features: optional ``(*batch, N, C)`` features, kept as they are.
            quat_order: ``"wxyz"`` (gsplat, 3DGS, GaussianFormer, dego) or ``"xyzw"``
                (scipy, PyTorch3D's ``*_xyzw``, many loaders); reordered to wxyz.
            rotation: which product the quaternion's matrix ``R`` enters. ``"R"``:
                ``Sigma = R diag(s^2) R^T`` (gsplat, 3DGS, dego; quaternion kept).
                ``"R^T"``: ``Sigma = R^T diag(s^2) R``, as GaussianFormer's
                ``(S R)^T (S R)``; stored as the conjugate ``(w, -x, -y, -z)``.
            scale_space: ``"std"`` (standard deviations, kept), ``"variance"`` (``sqrt``
                taken) or ``"log"`` (log standard deviations as 3DGS stores them; ``exp``).
            opacity_space: ``"prob"`` (in [0, 1], kept) or ``"logit"`` (``sigmoid`` taken).

        Unbatched input (``means.ndim == 2``) gets a batch axis: the result has batch shape
        ``(1,)``. Tensors that need no conversion are stored without copying. The values
        are checked with :meth:`check_values`, so e.g. logits passed as probabilities are
        caught here. Differentiable in every input.

        Raises:
            ValueError: an unknown option (named), negative variances, or invalid values.
        """
        _check_option("quat_order", quat_order, _QUAT_ORDERS)
        _check_option("rotation", rotation, _ROTATIONS)
        _check_option("scale_space", scale_space, _SCALE_SPACES)
        _check_option("opacity_space", opacity_space, _OPACITY_SPACES)
        if opacities.ndim == means.ndim:  # (*batch, N, 1); the annotation ensured the 1
            opacities = opacities.squeeze(-1)
        if quat_order == "xyzw":
            quats = quats.roll(1, dims=-1)
        if rotation == "R^T":
            quats = conjugate_quaternions(quats)
        if scale_space == "variance":
            negative = scales < 0
            if bool(negative.any()):
                raise ValueError(
                    f"scales: expected non-negative variances (scale_space='variance'), "
                    f"got {int(negative.sum())} negative values (e.g. "
                    f"{scales[negative][0].item():.6g})"
                )
            scales = scales.sqrt()
        elif scale_space == "log":
            scales = scales.exp()
        if opacity_space == "logit":
            opacities = torch.sigmoid(opacities)
        fields = {"means": means, "quats": quats, "scales": scales, "opacities": opacities}
        if features is not None:
            fields["features"] = features
        if means.ndim == 2:
            fields = {name: value.unsqueeze(0) for name, value in fields.items()}
        return cls(**fields).check_values()

    @typechecked
    def to_tensors(
        self,
        *,
        quat_order: str = "wxyz",
        rotation: str = "R",
        scale_space: str = "std",
        opacity_space: str = "prob",
        opacity_shape: str = "N",
    ) -> tuple[
        Float[Tensor, "*batch N 3"],
        Float[Tensor, "*batch N 4"],
        Float[Tensor, "*batch N 3"],
        Float[Tensor, "*batch N"] | Float[Tensor, "*batch N 1"],
        Float[Tensor, "*batch N C"] | None,
    ]:
        """``(means, quats, scales, opacities, features)`` in another code base's
        conventions: the inverse of :meth:`from_tensors` with the same options.

        Options as in :meth:`from_tensors` (``"xyzw"`` reorders, ``"R^T"`` conjugates,
        ``"variance"`` squares, ``"log"`` takes ``log``, ``"logit"`` applies
        ``torch.logit``), plus ``opacity_shape``: ``"N"`` for ``(*batch, N)`` or ``"N1"``
        for ``(*batch, N, 1)`` (gsplat/3DGS parameter layout). Shapes keep the set's batch
        axes (a set made from unbatched tensors returns ``(1, N, k)``: index ``[0]``).

        ``opacity_space="logit"`` maps opacity 0 to ``-inf`` and 1 to ``+inf`` (e.g. the
        zero-opacity padding of :meth:`stack`); ``from_tensors`` maps them back exactly,
        but clamp first (``replace(opacities=o.clamp(eps, 1 - eps))``) when finite
        logits are needed, e.g. to optimise them. Unconverted fields are returned without
        copying (they share storage with the set).

        Returns:
            ``means (*batch, N, 3)``, ``quats (*batch, N, 4)``, ``scales (*batch, N, 3)``,
            ``opacities (*batch, N)`` or ``(*batch, N, 1)``, ``features (*batch, N, C)``
            or ``None``.

        Raises:
            ValueError: an unknown option (named).
        """
        _check_option("quat_order", quat_order, _QUAT_ORDERS)
        _check_option("rotation", rotation, _ROTATIONS)
        _check_option("scale_space", scale_space, _SCALE_SPACES)
        _check_option("opacity_space", opacity_space, _OPACITY_SPACES)
        _check_option("opacity_shape", opacity_shape, _OPACITY_SHAPES)
        quats, scales, opacities = self.quats, self.scales, self.opacities
        if rotation == "R^T":
            quats = conjugate_quaternions(quats)
        if quat_order == "xyzw":
            quats = quats.roll(-1, dims=-1)
        if scale_space == "variance":
            scales = scales.square()
        elif scale_space == "log":
            scales = scales.log()
        if opacity_space == "logit":
            opacities = torch.logit(opacities)
        if opacity_shape == "N1":
            opacities = opacities.unsqueeze(-1)
        return self.means, quats, scales, opacities, self.features

    def items(self) -> list[tuple[str, Tensor]]:
        """``(name, tensor)`` for every present field, in declaration order."""
        return [(n, getattr(self, n)) for n in self.FIELDS if getattr(self, n) is not None]

    @typechecked
    def map(self, fn: Callable[[str, Tensor], Tensor]) -> GaussianSet:
        """A new set with ``fn(name, tensor)`` applied to every present field."""
        return GaussianSet(**{name: fn(name, value) for name, value in self.items()})

    # -- basic properties -------------------------------------------------------------
    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch shape ``*batch`` (empty for a single set)."""
        return self.means.shape[:-2]

    @property
    def num_gaussians(self) -> int:
        """Number N of Gaussians per batch element."""
        return self.means.shape[-2]

    @property
    def feature_dim(self) -> int | None:
        """Channel count C of ``features``, or ``None`` when there are no features."""
        return None if self.features is None else self.features.shape[-1]

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

    def __repr__(self) -> str:
        return (
            f"GaussianSet(batch_shape={tuple(self.batch_shape)}, "
            f"num_gaussians={self.num_gaussians}, feature_dim={self.feature_dim}, "
            f"dtype={self.dtype}, device={self.device})"
        )

    # -- geometry ---------------------------------------------------------------------
    def rotation_matrices(self) -> Float[Tensor, "*batch N 3 3"]:
        """Rotation matrices ``(*batch, N, 3, 3)`` of the (normalised) quaternions."""
        return rotation_matrices(self.quats)

    def covariances(self) -> Float[Tensor, "*batch N 3 3"]:
        """Covariances ``R diag(s^2) R^T``, ``(*batch, N, 3, 3)``."""
        return scaled_rotation_gram(self.quats, self.scales)

    def precisions(self) -> Float[Tensor, "*batch N 3 3"]:
        """Inverse covariances ``R diag(1/s^2) R^T``, ``(*batch, N, 3, 3)`` (no inversion).

        Needs positive scales: a scale <= 0 (or NaN) raises ``ValueError`` naming
        ``scales`` in eager mode (one host sync per call); under ``torch.compile`` the
        check is skipped and such a scale gives non-finite entries.
        """
        if not _is_compiling():
            _check_positive_scales(self.scales)
        return scaled_rotation_gram(self.quats, self.scales.reciprocal())

    # -- tensor plumbing --------------------------------------------------------------
    def to(self, *args: Any, **kwargs: Any) -> GaussianSet:
        """Apply ``Tensor.to(*args, **kwargs)`` to every field (device and/or float dtype)."""
        return self.map(lambda _, t: t.to(*args, **kwargs))

    def cpu(self) -> GaussianSet:
        """The set on the CPU."""
        return self.to("cpu")

    def cuda(self, device: int | str | torch.device | None = None) -> GaussianSet:
        """The set on a CUDA device (``None``: the current one), as ``Tensor.cuda``."""
        return self.map(lambda _, t: t.cuda(device))

    def float(self) -> GaussianSet:
        """Every field in float32."""
        return self.to(torch.float32)

    def double(self) -> GaussianSet:
        """Every field in float64."""
        return self.to(torch.float64)

    def half(self) -> GaussianSet:
        """Every field in float16."""
        return self.to(torch.float16)

    def bfloat16(self) -> GaussianSet:
        """Every field in bfloat16."""
        return self.to(torch.bfloat16)

    # -- batch and Gaussian axes ------------------------------------------------------
    def __len__(self) -> int:
        """The number of sets along the first batch axis (``B`` of a ``(B, N)`` set), as
        for pytorch3d's batched structures; an unbatched set has no length."""
        if not self.batch_shape:
            raise TypeError(
                "len() of an unbatched GaussianSet: it is one set; num_gaussians gives N"
            )
        return self.batch_shape[0]

    def __iter__(self) -> Iterator[GaussianSet]:
        """The sets along the first batch axis (``len(self)`` of them)."""
        return (self[i] for i in range(len(self)))

    def __getitem__(self, key: Any) -> GaussianSet:
        """Index the batch axes, then optionally the Gaussian axis N.

        ``gs[b]`` (an int, slice, integer or bool tensor, or a tuple of them over the batch
        axes) indexes the batch as a tensor of shape ``batch_shape`` would be; one more
        entry indexes N as :meth:`select` does: ``gs[0, :100]``, ``gs[:, mask]``,
        ``gs[..., idx]`` (``...`` stands for every batch axis). An int on N would drop
        the Gaussian axis and raises ``IndexError`` (use ``i:i + 1``). NumPy integer and
        bool arrays (and scalars) index as the same torch tensors would (they are moved
        to the set's device); any other index on N is a ``TypeError`` naming the accepted
        ones.
        """
        key = key if isinstance(key, tuple) else (key,)
        key = tuple(_numpy_index(k, self.device) for k in key)
        batch_axes = len(self.batch_shape)
        if any(k is Ellipsis for k in key):
            if len(key) != 2 or key[0] is not Ellipsis:
                raise IndexError(
                    "GaussianSet index: '...' is only allowed as gs[..., n] (every batch "
                    f"axis, then the Gaussian axis), got {key!r}"
                )
            batch_key, n_key = (), key[1]
        elif len(key) <= batch_axes:
            batch_key, n_key = key, None
        elif len(key) == batch_axes + 1:
            batch_key, n_key = key[:-1], key[-1]
        else:
            raise IndexError(
                f"GaussianSet index: {len(key)} indices for a set of batch shape "
                f"{tuple(self.batch_shape)} (at most {batch_axes + 1}: the batch axes, then N)"
            )
        if isinstance(n_key, int) or (isinstance(n_key, Tensor) and n_key.ndim == 0):
            raise IndexError(
                f"GaussianSet index: an int on the Gaussian axis N would drop it; use a slice "
                f"({n_key}:{n_key} + 1) or a sequence of indices"
            )
        if n_key is not None:
            _check_n_index(n_key)
        out = self if n_key is None else self.select(n_key)
        if batch_key:
            out = out.map(lambda _, t: t[batch_key])
        return out

    @float32_under_autocast()
    @typechecked
    def transformed(self, matrix: Float[Tensor, "*mbatch 4 4"]) -> GaussianSet:
        """The set under the rigid motion ``x -> R x + t`` of ``matrix`` (``(4, 4)`` or
        one per batch item, ``(*batch, 4, 4)``): means move, orientations rotate, scales,
        opacities and features are unchanged. E.g. world -> ego of another frame."""
        if matrix.shape[:-2] not in ((), tuple(self.batch_shape)):
            raise ValueError(
                f"matrix: expected shape (4, 4) or (*batch, 4, 4) with batch "
                f"{tuple(self.batch_shape)}, got {tuple(matrix.shape)}"
            )
        matrix = matrix.to(self.means)
        r = matrix[..., :3, :3]
        identity = torch.eye(3, dtype=r.dtype, device=r.device)
        tolerance = 1e-4 if r.dtype == torch.float32 else 1e-8
        if not bool(torch.isfinite(matrix).all()) or not bool(
            ((r @ r.transpose(-1, -2) - identity).abs() <= tolerance).all()
            & (torch.linalg.det(r) > 0).all()
        ):
            raise ValueError(
                "matrix: expected finite rigid motions (a rotation in the upper-left 3x3, "
                "orthonormal with determinant +1)"
            )
        rotation, translation = matrix[..., None, :3, :3], matrix[..., None, :3, 3]
        means = (rotation @ self.means.unsqueeze(-1)).squeeze(-1) + translation
        turn = rotation_matrices_to_quaternions(r)[..., None, :]
        return dataclasses.replace(self, means=means, quats=quaternion_product(turn, self.quats))

    def detach(self) -> GaussianSet:
        """A copy whose tensors are detached from the autograd graph."""
        return self.map(lambda _, t: t.detach())

    @typechecked
    def replace(self, **fields: Tensor | None) -> GaussianSet:
        """A new set with some fields replaced (re-validated); ``features=None`` drops features."""
        unknown = sorted(set(fields) - set(self.FIELDS))
        if unknown:
            raise TypeError(f"replace: unknown field(s) {unknown}; valid fields are {self.FIELDS}")
        return dataclasses.replace(self, **fields)  # type: ignore[arg-type]  # None drops features

    @typechecked
    def select(
        self,
        index: slice
        | Sequence[int]
        | Int[Tensor, "*index_shape"]
        | Bool[Tensor, " N"]
        | Integer[np.ndarray, "*index_shape"]
        | Bool[np.ndarray, " N"],
    ) -> GaussianSet:
        """Gaussians picked along N.

        ``index`` may be a slice, a sequence of ints, a 1-D integer tensor (shared by the
        whole batch; negative values count from the end), a 1-D bool mask of length N,
        or an integer tensor of shape ``(*batch, K)`` picking K Gaussians per batch item.
        NumPy integer / bool arrays are taken as those tensors.
        """
        n = self.num_gaussians
        if isinstance(index, np.ndarray):
            index = _numpy_index(index, self.device)
        if isinstance(index, slice):
            index = torch.arange(n, device=self.device)[index]
        elif not isinstance(index, Tensor):
            if isinstance(index, str | bytes) or not all(
                isinstance(i, int) and not isinstance(i, bool) for i in index
            ):
                raise TypeError("index: a sequence index must hold ints only")
            index = torch.tensor(list(index), dtype=torch.long)
        index = index.to(self.device)
        if index.dtype == torch.bool:
            if index.shape[0] != n:
                raise ValueError(f"index: bool mask has length {index.shape[0]}, expected N={n}")
            index = index.nonzero().squeeze(-1)
        out_of_range = (index < -n) | (index >= n)
        if index.numel() and bool(out_of_range.any()):
            bad = index[out_of_range][0].item()
            raise IndexError(f"index: value {bad} is out of range for N={n}")
        index = index.long().remainder(n) if n else index.long()
        if index.ndim == 1:
            return self.map(lambda name, t: t.index_select(_gaussian_axis(name, t), index))
        if tuple(index.shape[:-1]) != tuple(self.batch_shape):
            raise ValueError(
                f"index: a batched index must have shape (*batch, K) with batch "
                f"{tuple(self.batch_shape)}, got {tuple(index.shape)}"
            )

        def gather(name: str, t: Tensor) -> Tensor:
            along = index if name == "opacities" else index.unsqueeze(-1)
            return torch.take_along_dim(t, along, dim=_gaussian_axis(name, t))

        return self.map(gather)

    @staticmethod
    @typechecked
    def cat(sets: Sequence[GaussianSet]) -> GaussianSet:
        """Concatenate sets along N; they must share batch shape, dtype, device and features."""
        if len(sets) == 0:
            raise ValueError("sets: need at least one GaussianSet to concatenate")
        first = sets[0]
        for i, s in enumerate(sets):
            if not isinstance(s, GaussianSet):
                raise TypeError(f"sets[{i}]: expected a GaussianSet, got {type(s).__name__}")
            if s.batch_shape != first.batch_shape:
                raise ValueError(
                    f"sets[{i}]: batch shape {tuple(s.batch_shape)} differs from sets[0]'s "
                    f"{tuple(first.batch_shape)}"
                )
            if s.feature_dim != first.feature_dim:
                raise ValueError(
                    f"sets[{i}]: feature_dim {s.feature_dim} differs from sets[0]'s "
                    f"{first.feature_dim} (all sets need features of one size, or none)"
                )
            if s.dtype != first.dtype or s.device != first.device:
                raise ValueError(
                    f"sets[{i}]: {s.dtype} on {s.device} differs from sets[0]'s "
                    f"{first.dtype} on {first.device}"
                )
        return first.map(
            lambda name, t: torch.cat([getattr(s, name) for s in sets], _gaussian_axis(name, t))
        )

    @staticmethod
    @typechecked
    def stack(sets: Sequence[GaussianSet]) -> GaussianSet:
        """Stack unbatched sets of possibly different N into one ``(len(sets), N_max)`` batch.

        Shorter sets are padded with zero-opacity Gaussians (mean 0, identity rotation,
        unit scale, zero features), which by the library's contract contribute nothing.
        """
        if len(sets) == 0:
            raise ValueError("sets: need at least one GaussianSet to stack")
        for i, s in enumerate(sets):
            if not isinstance(s, GaussianSet) or s.batch_shape != ():
                raise ValueError(f"sets[{i}]: expected an unbatched GaussianSet (batch_shape ())")
        GaussianSet.cat(sets)  # validates feature_dim / dtype / device agreement
        n_max = max(s.num_gaussians for s in sets)
        padded = [GaussianSet.cat([s, _padding_like(s, n_max - s.num_gaussians)]) for s in sets]
        return padded[0].map(lambda name, _: torch.stack([getattr(s, name) for s in padded]))

    def reshape_batch(self, *shape: int) -> GaussianSet:
        """Reshape the batch axes to ``shape`` (``-1`` allowed); N and channels are kept."""

        def reshape(name: str, t: Tensor) -> Tensor:
            tail = t.shape[len(self.batch_shape) :]
            return t.reshape(*shape, *tail)

        try:
            return self.map(reshape)
        except RuntimeError as err:
            raise ValueError(
                f"shape: cannot reshape batch {tuple(self.batch_shape)} to {shape}"
            ) from err

    def flatten_batch(self) -> GaussianSet:
        """Merge all batch axes into one: ``(*batch, N, k) -> (prod(batch), N, k)``.

        An unbatched set becomes a batch of one.
        """
        return self.reshape_batch(math.prod(self.batch_shape))

    # -- value checks -----------------------------------------------------------------
    def check_values(self) -> GaussianSet:
        """Raise ``ValueError`` on non-finite values, scales <= 0, opacities outside [0, 1]
        or zero-norm quaternions; returns ``self`` so it can be chained.

        When every opacity lies outside [0, 1] or every scale is negative, the message
        says they look like logits / log-scales and points to :meth:`from_tensors`.
        """
        run_checks(
            [finite_check(name, value) for name, value in self.items()]
            + gaussian_value_checks(
                "", scales=self.scales, opacities=self.opacities, quats=self.quats
            )
        )
        return self


_N_INDEX_TYPES = "a slice, a sequence of ints, or an integer or bool torch.Tensor / numpy.ndarray"


def _numpy_index(key: Any, device: torch.device) -> Any:
    """A NumPy integer / bool index (array or scalar) as the tensor torch would index with,
    on ``device``; any other ``key`` unchanged."""
    if not isinstance(key, np.ndarray | np.generic) or key.dtype.kind not in "iub":
        return key
    if key.dtype.kind == "u":  # no unsigned index tensors in torch (uint8 would be a mask)
        key = np.asarray(key, dtype=np.int64)
    return torch.as_tensor(key, device=device)


def _check_n_index(key: Any) -> None:
    """``TypeError`` (one line) unless ``key`` is an index :meth:`GaussianSet.select` takes."""
    if isinstance(key, slice):
        return
    if isinstance(key, Tensor):
        if key.dtype == torch.bool or not (key.is_floating_point() or key.is_complex()):
            return
        got = f"a {key.dtype} tensor"
    elif isinstance(key, np.ndarray | np.generic):
        got = f"a numpy {type(key).__name__} of dtype {key.dtype}"
    elif isinstance(key, Sequence) and not isinstance(key, str | bytes):
        if all(isinstance(i, int) and not isinstance(i, bool) for i in key):
            return
        got = "a sequence that holds other values than ints"
    else:
        got = type(key).__name__
    raise TypeError(f"GaussianSet index: the Gaussian axis N takes {_N_INDEX_TYPES}; got {got}")


def _autocast_features(name: str, value: Tensor, means: Tensor) -> bool:
    """Half-precision ``features`` beside float32 geometry while autocast is on for their
    device: a network's output under autocast. The ops that need float32 (``splat``,
    ``voxelize``, ...) cast them; the set's ``dtype`` is the geometry's."""
    return (
        name == "features"
        and value.dtype in HALF_DTYPES
        and means.dtype == torch.float32
        and autocast_enabled(value.device.type)
    )


def _gaussian_axis(name: str, t: Tensor) -> int:
    """Index of the N axis of field ``name`` (opacities have no trailing channel axis)."""
    return t.ndim - 1 if name == "opacities" else t.ndim - 2


def _padding_like(s: GaussianSet, count: int) -> GaussianSet:
    means = s.means.new_zeros(count, 3)
    quats = s.means.new_zeros(count, 4)
    quats[:, 0] = 1
    features = None if s.features is None else s.means.new_zeros(count, s.features.shape[-1])
    return GaussianSet(
        means=means,
        quats=quats,
        scales=s.means.new_ones(count, 3),
        opacities=s.means.new_zeros(count),
        features=features,
    )


# -- torch pytree registration ---------------------------------------------------------


def _flatten(gs: GaussianSet) -> tuple[list[Any], tuple[str, ...]]:
    names = tuple(n for n in GaussianSet.FIELDS if getattr(gs, n) is not None)
    return [getattr(gs, n) for n in names], names


def _flatten_with_keys(gs: GaussianSet) -> tuple[list[tuple[Any, Any]], tuple[str, ...]]:
    leaves, names = _flatten(gs)
    return [(pytree.GetAttrKey(n), leaf) for n, leaf in zip(names, leaves, strict=True)], names


def _unflatten(leaves: Any, names: tuple[str, ...]) -> GaussianSet:
    return GaussianSet._unchecked(**dict(zip(names, leaves, strict=True)))


pytree.register_pytree_node(
    GaussianSet,
    _flatten,
    _unflatten,
    serialized_type_name="dego.GaussianSet",
    to_dumpable_context=list,
    from_dumpable_context=tuple,
    flatten_with_keys_fn=_flatten_with_keys,
)

__all__ = [
    "QUATERNION_EPS",
    "GaussianSet",
    "build_covariances",
    "build_precisions",
    "normalize_quaternions",
    "quaternions_to_rotation_matrices",
    "rotation_matrices_to_quaternions",
]
