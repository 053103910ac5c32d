"""Voxel confusion matrices for semantic occupancy, computed in one vectorised pass.

Label grids may be torch tensors (CPU or CUDA) or numpy arrays of any integer dtype
(Occ3D ships uint8). The matrix has rows = ground truth and columns = prediction, as
in the Occ3D devkit's ``np.bincount(C * gt + pred)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from dego._policy import run_checks
from dego._typing import _is_compiling, typechecked

_SMALL_INTS = (torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)


def _native(array: np.ndarray) -> np.ndarray:
    """A contiguous, writable, native-byte-order view or copy that torch can wrap."""
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    array = np.ascontiguousarray(array)
    return array if array.flags.writeable else array.copy()


def as_label_tensor(name: str, labels: Tensor | np.ndarray) -> Tensor:
    """``labels`` as an integer tensor (numpy converted without copy where possible).

    Raises ``TypeError`` naming ``name`` for floating, bool or non-array input.
    """
    if isinstance(labels, np.ndarray):
        labels = torch.from_numpy(_native(labels))
    if not isinstance(labels, Tensor):
        raise TypeError(
            f"{name}: expected a torch.Tensor or numpy array of integer labels, "
            f"got {type(labels).__name__}"
        )
    if labels.dtype == torch.bool or labels.is_floating_point() or labels.is_complex():
        raise TypeError(f"{name}: expected integer labels, got dtype {labels.dtype}")
    if labels.dtype not in _SMALL_INTS:  # uint16/32/64 lack most kernels
        labels = labels.to(torch.int64)
    return labels


def as_mask_tensor(mask: Tensor | np.ndarray, shape: torch.Size, device: torch.device) -> Tensor:
    """A bool mask of ``shape``; a uint8 mask is accepted only if it holds 0 and 1.

    Indexing with a uint8 mask as integers is the classic numpy pitfall that silently
    evaluates the wrong voxels; here it is either a valid 0/1 mask or an error.
    """
    if isinstance(mask, np.ndarray):
        mask = torch.from_numpy(_native(mask))
    if not isinstance(mask, Tensor):
        raise TypeError(
            f"mask: expected a bool torch.Tensor or numpy array, got {type(mask).__name__}"
        )
    if mask.shape != shape:
        raise ValueError(f"mask: shape {tuple(mask.shape)} does not match gt's {tuple(shape)}")
    if mask.dtype == torch.uint8:
        if mask.numel() and int(mask.max()) > 1:
            raise ValueError(
                f"mask: a uint8 mask must hold only 0 and 1, found {int(mask.max())}; "
                "convert it with mask.astype(bool) / mask.bool() if non-zero means valid"
            )
        mask = mask.bool()
    elif mask.dtype != torch.bool:
        raise TypeError(f"mask: expected dtype bool (or uint8 holding 0/1), got {mask.dtype}")
    return mask.to(device)


def labels_in_range(labels: Tensor, num_classes: int) -> bool:
    """Whether every label lies in ``0..num_classes-1``, known in one pass (and the one
    host sync) in eager mode; ``False`` under torch.compile, where the caller's in-graph
    check decides."""
    if _is_compiling():
        return False
    low, high = (int(v) for v in torch.aminmax(labels))
    return low >= 0 and high < num_classes


def _check_range(name: str, labels: Tensor, num_classes: int, allowed: int | None) -> None:
    if labels.numel() == 0 or labels_in_range(labels, num_classes):
        return
    bad = (labels < 0) | (labels >= num_classes)
    if allowed is not None:
        bad &= labels != allowed

    def error() -> Exception:
        value = int(labels[bad][0])
        extra = f" or the ignore label {allowed}" if allowed is not None else ""
        return ValueError(
            f"{name}: label {value} is out of range; expected 0..{num_classes - 1}{extra}"
        )

    run_checks([(~bad.any(), f"{name}: a label is out of range 0..{num_classes - 1}", error)])


@typechecked
def confusion_matrix(
    pred: Tensor | np.ndarray,
    gt: Tensor | np.ndarray,
    mask: Tensor | np.ndarray | None = None,
    *,
    num_classes: int = 18,
    ignore_label: int | np.integer | None = 255,
    removed_classes: Sequence[int] = (),
) -> Tensor:
    """``(C, C)`` int64 confusion matrix (rows gt, columns pred) over the evaluated voxels.

    Args:
        pred: predicted labels, any shape (an empty batch gives a zero matrix) and any
            integer dtype (uint8 as Occ3D ships them, int8 ... int64: the counts do not
            depend on it); values in ``0..C-1``.
        gt: ground-truth labels, same shape; values in ``0..C-1`` or ``ignore_label``.
        mask: optional bool (or 0/1 uint8) mask of the same shape; False voxels are skipped.
        num_classes: C.
        ignore_label: gt value whose voxels are skipped (``None``: no such value). Any int
            outside ``0..C-1``: 255 (the default), -1, or a large value.
        removed_classes: gt classes whose voxels are skipped as well (the weakly
            supervised protocol removes 0 ``others`` and 12 ``other_flat``).

    Returns the matrix on ``gt``'s device.

    Raises:
        TypeError: bool, floating or non-array labels.
        ValueError: a label out of range (naming ``pred`` or ``gt`` and the value; the
            ignore label is not a valid prediction), an ``ignore_label`` inside
            ``0..C-1``, shape or device mismatches.
    """
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise ValueError(f"num_classes: expected an int >= 1, got {num_classes!r}")
    ignore_label = check_ignore_label(ignore_label, num_classes)
    pred, gt = as_label_tensor("pred", pred), as_label_tensor("gt", gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred: shape {tuple(pred.shape)} does not match gt's {tuple(gt.shape)}")
    if pred.device != gt.device:
        raise ValueError(f"pred: on {pred.device} but gt is on {gt.device}")
    _check_range("gt", gt, num_classes, ignore_label)
    _check_range("pred", pred, num_classes, None)

    # key = C * gt + pred, counted with one bincount and no boolean gather (which would
    # dominate the cost). Keys of ignored gt are >= C * C and those of masked-out voxels
    # are shifted past every label key; both land beyond the C * C bins that are kept.
    # Voxels of removed gt classes only ever reach those classes' rows, which are zeroed.
    # An ignore label that no voxel of gt's dtype can hold (255 in int8, -1 in uint8) is
    # no ignore label at all; one below 0 or above 255 is first replaced by C, so that
    # every key stays small and non-negative.
    info = torch.iinfo(gt.dtype)
    if ignore_label is not None and not info.min <= ignore_label <= info.max:
        ignore_label = None
    direct = ignore_label is None or 0 <= ignore_label <= 255
    # the largest gt value left in the keys: a class, or the ignore label (direct or as C)
    max_label = num_classes - 1 if ignore_label is None else num_classes
    if ignore_label is not None and direct:
        max_label = max(num_classes - 1, ignore_label)
    span = num_classes * (max_label + 1)
    key_dtype = torch.int16 if 2 * span <= torch.iinfo(torch.int16).max else torch.int64
    gt_key = gt.to(key_dtype)
    if ignore_label is not None and not direct:
        gt_key = gt_key.masked_fill(gt == ignore_label, num_classes)
    key = torch.add(pred.to(key_dtype), gt_key, alpha=num_classes)
    if mask is not None:
        outside = as_mask_tensor(mask, gt.shape, gt.device).logical_not()
        key.add_(outside.to(key_dtype), alpha=span)
    bins = num_classes * num_classes
    flat = key.reshape(-1)
    if _is_compiling():  # bincount's output length depends on the data: no graph break
        histogram = torch.zeros(2 * span, dtype=torch.int64, device=flat.device)
        histogram.scatter_add_(0, flat.long(), torch.ones_like(flat, dtype=torch.int64))
    else:
        histogram = torch.bincount(flat, minlength=bins)
    counts = histogram[:bins].reshape(num_classes, num_classes)
    if removed_classes:
        counts[list(removed_classes)] = 0
    return counts


def check_ignore_label(ignore_label: object, num_classes: int) -> int | None:
    """``ignore_label`` as an int outside ``0..num_classes-1`` (or ``None``)."""
    if ignore_label is None:
        return None
    if isinstance(ignore_label, bool) or not isinstance(ignore_label, int | np.integer):
        raise ValueError(f"ignore_label: expected an int or None, got {ignore_label!r}")
    ignore_label = int(ignore_label)
    if 0 <= ignore_label < num_classes:
        raise ValueError(
            f"ignore_label: {ignore_label} collides with a class in 0..{num_classes - 1}"
        )
    return ignore_label


@typechecked
def binary_occupancy_confusion(confusion: Tensor, free_label: int) -> Tensor:
    """``(2, 2)`` occupied/free matrix (index 0 occupied, 1 free; rows gt) from a ``(C, C)`` one.

    Equal to relabelling gt and pred as ``label != free -> 0``, ``free -> 1`` on the same
    voxels and counting, as the reference geometric IoU does.

    Raises:
        TypeError: ``confusion`` not a square integer matrix.
        ValueError: ``free_label`` outside ``0..C-1``.
    """
    if confusion.ndim != 2 or confusion.shape[0] != confusion.shape[1]:
        raise TypeError(f"confusion: expected a (C, C) matrix, got {tuple(confusion.shape)}")
    if confusion.is_floating_point() or confusion.is_complex() or confusion.dtype == torch.bool:
        raise TypeError(f"confusion: expected integer counts, got {confusion.dtype}")
    if isinstance(free_label, bool) or not 0 <= free_label < confusion.shape[0]:
        raise ValueError(
            f"free_label: expected an int in 0..{confusion.shape[0] - 1}, got {free_label!r}"
        )
    is_free = torch.zeros(confusion.shape[0], dtype=torch.long, device=confusion.device)
    is_free[free_label] = 1
    out = torch.zeros(2, 2, dtype=confusion.dtype, device=confusion.device)
    pairs = (is_free.unsqueeze(1) * 2 + is_free.unsqueeze(0)).reshape(-1)
    return out.view(-1).index_add_(0, pairs, confusion.reshape(-1)).view(2, 2)


__all__ = ["as_label_tensor", "as_mask_tensor", "binary_occupancy_confusion", "confusion_matrix"]
