"""Teacher tokens -> distillation target maps ``(B, V, C_a, H, W)`` (DeGO section 4.2)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from dego._checks import check_int
from dego._policy import check_dtype, check_memory, compute_dtype
from dego._typing import typechecked
from dego.teacher.factorized import TeacherOutput

Projector = Literal["frozen", "trainable"]


class FactorizedTeacherFeatures(nn.Module):
    """Select, reshape, project and upsample teacher tokens into distillation targets.

    For block ``layer`` and time index ``reference_time``, the special tokens are dropped,
    the patch tokens are laid out on the patch grid ``(H', W')``, the spatial and temporal
    halves are concatenated (``[spatial; temporal]``, 2C = ``in_dim`` channels), projected
    to ``out_dim`` = C_a per patch, and bilinearly upsampled (``align_corners=False``) to
    the render size.

    Accepted teacher outputs:

    - a :class:`TeacherOutput` of :class:`FactorizedSpatioTemporalTeacher` (its own
      ``patch_start_idx`` and patch grid are used);
    - VGGT-layout aggregator outputs: a sequence of per-block ``(B, S, P, 2C)`` tensors with
      S = T V images in time-major order (image ``s = t V + v``) whose channels are already
      the two halves concatenated, ``patch_start_idx`` special tokens first (VGGT: 5); pass
      ``patch_grid`` and ``num_cameras``.

    Projectors:

    - ``"frozen"`` (default): a bias-free linear map with orthonormal rows (or columns),
      drawn from ``seed`` and never trained (a buffer, no parameters). The targets are then
      a fixed function of the teacher, so the distillation loss has no trivial minimum.
    - ``"trainable"``: ``nn.Linear(in_dim, out_dim)`` with bias, as in the official code.
      Under a pure cosine loss it admits a collapsed solution: zero weights and a bias
      equal to a constant student output give zero loss whatever the teacher says. Use it
      only with a stop-gradient, a variance term or similar.
    """

    weight: Tensor  # the buffer of projector="frozen"

    def __init__(
        self,
        in_dim: int,
        out_dim: int = 32,
        *,
        layer: int = -1,
        reference_time: int = 0,
        patch_start_idx: int = 0,
        projector: Projector = "frozen",
        seed: int = 0,
    ) -> None:
        super().__init__()
        for name, value, low in [
            ("in_dim", in_dim, 1),
            ("out_dim", out_dim, 1),
            ("patch_start_idx", patch_start_idx, 0),
        ]:
            check_int(name, value, low)
        check_int("layer", layer)
        check_int("reference_time", reference_time)
        if projector not in ("frozen", "trainable"):
            raise ValueError(f"projector: expected 'frozen' or 'trainable', got {projector!r}")
        self.in_dim, self.out_dim = in_dim, out_dim
        self.layer, self.reference_time = layer, reference_time
        self.patch_start_idx = patch_start_idx
        self.projector: Projector = projector
        if projector == "trainable":
            self.linear = nn.Linear(in_dim, out_dim)
        else:
            generator = torch.Generator().manual_seed(seed)
            weight = torch.empty(out_dim, in_dim)
            nn.init.orthogonal_(weight, generator=generator)
            self.register_buffer("weight", weight)

    @typechecked
    def project(self, maps: Float[Tensor, "*batch C H W"]) -> Tensor:
        """Apply the projector per pixel: ``(*, in_dim, H, W)`` -> ``(*, out_dim, H, W)``."""
        x = maps.movedim(-3, -1)
        frozen = self.projector == "frozen"
        x = F.linear(x, self.weight.to(x.dtype)) if frozen else self.linear(x)
        return x.movedim(-1, -3)

    @typechecked
    def select(
        self,
        teacher: TeacherOutput | Sequence[Tensor],
        *,
        patch_grid: tuple[int, int] | None = None,
        num_cameras: int | None = None,
    ) -> Float[Tensor, "B V C2 Hp Wp"]:
        """The unprojected teacher maps ``(B, V, in_dim, H', W')`` at ``reference_time``."""
        if isinstance(teacher, TeacherOutput):
            spatial = _pick(teacher.spatial, self.layer, "layer")
            temporal = _pick(teacher.temporal, self.layer, "layer")
            for name, block in (("spatial", spatial), ("temporal", temporal)):
                if block.ndim != 5:
                    raise ValueError(
                        f"teacher: expected {name} blocks (B, T, V, P, C), got {tuple(block.shape)}"
                    )
            if temporal.shape != spatial.shape:
                raise ValueError(
                    f"teacher: temporal block {tuple(temporal.shape)} differs from spatial "
                    f"block {tuple(spatial.shape)}"
                )
            check_dtype("teacher", temporal, spatial.dtype, "its spatial blocks")
            time = self._time(spatial.shape[1])
            tokens = torch.cat([spatial[:, time], temporal[:, time]], -1)  # (B, V, P, 2C)
            start, grid = teacher.patch_start_idx, teacher.patch_grid
        else:
            if patch_grid is None or num_cameras is None:
                raise ValueError(
                    "patch_grid, num_cameras: both are required with VGGT-layout outputs"
                )
            if len(patch_grid) != 2 or any(
                isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in patch_grid
            ):
                raise ValueError(f"patch_grid: expected (H', W') ints >= 1, got {patch_grid!r}")
            block = _pick(list(teacher), self.layer, "layer")
            if block.ndim != 4:
                raise ValueError(
                    f"teacher: expected per-block tensors (B, S, P, 2C), got {tuple(block.shape)}"
                )
            b, s = block.shape[:2]
            if num_cameras < 1 or s % num_cameras:
                raise ValueError(
                    f"num_cameras: S = {s} images are not a whole number of {num_cameras} cameras"
                )
            t = s // num_cameras
            time = self._time(t)
            tokens = block.view(b, t, num_cameras, *block.shape[2:])[:, time]
            start, grid = self.patch_start_idx, (patch_grid[0], patch_grid[1])
        rows, cols = grid
        if tokens.shape[-2] != start + rows * cols:
            raise ValueError(
                f"teacher: {tokens.shape[-2]} tokens per image, expected patch_start_idx "
                f"{start} + {rows} x {cols} patches"
            )
        if tokens.shape[-1] != self.in_dim:
            raise ValueError(
                f"teacher: {tokens.shape[-1]} channels ([spatial; temporal]), expected in_dim "
                f"{self.in_dim}"
            )
        patches = tokens[..., start:, :]  # (B, V, H' W', 2C)
        return patches.unflatten(-2, (rows, cols)).movedim(-1, -3)

    def _time(self, t: int) -> int:
        """``reference_time`` as an index into T time steps."""
        if t == 0:
            raise ValueError(
                f"teacher: holds T = 0 time steps; reference_time={self.reference_time} "
                "needs at least one"
            )
        return _index(self.reference_time, t, "reference_time")

    @typechecked
    def forward(
        self,
        teacher: TeacherOutput | Sequence[Tensor],
        output_size: tuple[int, int],
        *,
        patch_grid: tuple[int, int] | None = None,
        num_cameras: int | None = None,
    ) -> Float[Tensor, "B V C H W"]:
        """Distillation targets ``(B, V, out_dim, H, W)`` at ``output_size = (H, W)``.

        ``teacher``: see the class description. Its tokens give the dtype (the frozen
        projector follows it; the trainable one must share it) and an empty batch or
        camera axis (B or V = 0) gives an empty result. With the frozen projector,
        float16 / bfloat16 tokens are computed in float32 and returned in their dtype.
        The output's size goes through dego's memory guard before it is allocated.

        Raises:
            TypeError: the teacher's blocks differ in dtype, or differ from the trainable
                projector's.
            ValueError: a malformed teacher (no blocks, T = 0 time steps, wrong token or
                channel counts), a bad ``output_size``, ``patch_grid`` or
                ``num_cameras``, or an output above the memory limit.
            IndexError: ``layer`` or ``reference_time`` out of range.
        """
        if (
            len(output_size) != 2
            or any(isinstance(n, bool) or not isinstance(n, int) for n in output_size)
            or min(output_size) < 1
        ):
            raise ValueError(f"output_size: expected (H, W) ints >= 1, got {output_size!r}")
        selected = self.select(teacher, patch_grid=patch_grid, num_cameras=num_cameras)
        if self.projector == "trainable":
            check_dtype("teacher", selected, self.linear.weight.dtype, "the projector")
        b, v = selected.shape[:2]
        check_memory(
            "FactorizedTeacherFeatures",
            selected.element_size() * b * v * self.out_dim * output_size[0] * output_size[1],
            f"B*V = {b}*{v} maps of {self.out_dim} channels x {output_size[0]} x "
            f"{output_size[1]}, {selected.dtype}",
        )
        dtype = selected.dtype
        if self.projector == "frozen":  # float16 / bfloat16: computed in float32
            selected = selected.to(compute_dtype(dtype))
        maps = self.project(selected)  # (B, V, C_a, H', W')
        upsampled = F.interpolate(
            maps.flatten(0, 1), size=tuple(output_size), mode="bilinear", align_corners=False
        )
        return upsampled.view(*maps.shape[:3], *output_size).to(dtype)

    def extra_repr(self) -> str:
        return (
            f"in_dim={self.in_dim}, out_dim={self.out_dim}, layer={self.layer}, "
            f"reference_time={self.reference_time}, projector={self.projector!r}"
        )


def _index(i: int, size: int, name: str) -> int:
    if not -size <= i < size:
        raise IndexError(f"{name}: {i} is out of range for {size} entries")
    return i % size


def _pick(blocks: Sequence[Tensor], layer: int, name: str) -> Tensor:
    if len(blocks) == 0:
        raise ValueError("teacher: holds no blocks")
    return blocks[_index(layer, len(blocks), name)]


__all__ = ["FactorizedTeacherFeatures", "Projector"]
