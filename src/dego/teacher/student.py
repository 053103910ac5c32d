"""Student projector: per-Gaussian features C_g -> distillation space C_a, before splatting."""

from __future__ import annotations

from jaxtyping import Float
from torch import Tensor, nn

from dego._checks import check_int
from dego._policy import check_dtype
from dego._typing import typechecked


class StudentProjector(nn.Module):
    """Maps per-Gaussian features ``(*batch, C_g)`` to ``(*batch, C_a)`` for rendering.

    The projected features are splatted into the cameras and compared with the teacher
    maps by :func:`~dego.teacher.loss.distillation_loss`. Projecting per Gaussian before
    splatting (rather than per pixel after) keeps the render at C_a channels.

    Args:
        in_dim: C_g, the per-Gaussian feature width.
        out_dim: C_a, the distillation width (32 in the paper).
        hidden_dim: ``None`` (default) for a single ``Linear(C_g, C_a)``; an int for
            ``Linear(C_g, hidden) -> LeakyReLU -> Linear(hidden, C_a)``. The official
            student head is deeper, ``Linear(256, 512) -> LeakyReLU -> Linear(512, 512) ->
            LeakyReLU -> Linear(512, 32)``; stack modules for that exact layout.
        negative_slope: LeakyReLU slope of the hidden variant (torch's default 0.01).

    Flatten extra axes (time, cameras) into the leading ``*batch`` axes; any number works,
    including empty ones (a ``(0, C_g)`` input gives ``(0, C_a)``). Inputs must share the
    parameters' dtype (``TypeError`` otherwise) and device (``ValueError``).
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int = 32,
        *,
        hidden_dim: int | None = None,
        negative_slope: float = 0.01,
    ) -> None:
        super().__init__()
        self.in_dim = check_int("in_dim", in_dim, 1)
        self.out_dim = check_int("out_dim", out_dim, 1)
        self.hidden_dim = None if hidden_dim is None else check_int("hidden_dim", hidden_dim, 1)
        if isinstance(negative_slope, bool) or not isinstance(negative_slope, (int, float)):
            raise ValueError(f"negative_slope: expected a float, got {negative_slope!r}")
        if self.hidden_dim is None:
            self.net: nn.Module = nn.Linear(in_dim, out_dim)
        else:
            self.net = nn.Sequential(
                nn.Linear(in_dim, self.hidden_dim),
                nn.LeakyReLU(float(negative_slope)),
                nn.Linear(self.hidden_dim, out_dim),
            )

    @typechecked
    def forward(self, features: Float[Tensor, "*batch C_g"]) -> Float[Tensor, "*batch C_a"]:
        """Project ``(*batch, C_g)`` per-Gaussian features to ``(*batch, C_a)``."""
        if features.shape[-1] != self.in_dim:
            raise ValueError(
                f"features: expected {self.in_dim} channels in the last axis, "
                f"got shape {tuple(features.shape)}"
            )
        weight = next(self.parameters())
        check_dtype("features", features, weight.dtype, "StudentProjector")
        if features.device != weight.device:
            raise ValueError(
                f"features: on device {features.device} but the projector is on {weight.device}"
            )
        return self.net(features)

    def extra_repr(self) -> str:
        return f"in_dim={self.in_dim}, out_dim={self.out_dim}, hidden_dim={self.hidden_dim}"


__all__ = ["StudentProjector"]
