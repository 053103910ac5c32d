"""Factorized spatio-temporal teacher and its target maps: mixing across cameras and
frames (with a negative control), reduction to per-image attention, RoPE, VGGT-layout
placement, projectors and the collapse risk, bad input."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

import dego
from dego.teacher import (
    FactorizedSpatioTemporalTeacher,
    FactorizedTeacherFeatures,
    TeacherOutput,
    rotary_2d,
)
from dego.teacher.loss import distillation_loss

PATCH = 4


def small_teacher(
    depth: int = 2, dtype: torch.dtype = torch.float64
) -> FactorizedSpatioTemporalTeacher:
    torch.manual_seed(0)
    return FactorizedSpatioTemporalTeacher(32, depth, 2, PATCH).to(dtype)


def clip(b: int, t: int, v: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, t, v, 3, 2 * PATCH, 3 * PATCH, generator=g, dtype=dtype)


# ---------------------------------------------------------------------------------------
# mixing
# ---------------------------------------------------------------------------------------


def test_perturbing_another_camera_at_the_same_time_changes_the_spatial_output() -> None:
    teacher, images = small_teacher(), clip(1, 3, 3)
    base = teacher(images)
    perturbed = images.clone()
    perturbed[0, 0, 2] += 0.3  # camera 2 at time 0
    out = teacher(perturbed)
    for block in range(2):
        change = (out.spatial[block][0, 0, 0] - base.spatial[block][0, 0, 0]).abs().max()
        assert change > 1e-4  # camera 0 at time 0 saw camera 2
    # cameras at other times are untouched by the first spatial attention
    assert torch.equal(out.spatial[0][0, 1], base.spatial[0][0, 1])


def test_perturbing_the_same_camera_at_another_time_changes_the_temporal_output() -> None:
    teacher, images = small_teacher(), clip(1, 3, 2)
    base = teacher(images)
    perturbed = images.clone()
    perturbed[0, 2, 1] += 0.3  # camera 1 at time 2
    out = teacher(perturbed)
    # the first spatial attention at time 0 cannot see time 2 ...
    assert torch.equal(out.spatial[0][0, 0], base.spatial[0][0, 0])
    # ... the first temporal attention can
    assert (out.temporal[0][0, 0, 1] - base.temporal[0][0, 0, 1]).abs().max() > 1e-4
    # and through it the next block reaches the other cameras at time 0
    assert (out.spatial[1][0, 0, 0] - base.spatial[1][0, 0, 0]).abs().max() > 1e-4


def test_negative_control_cameras_stacked_on_the_batch_axis_do_not_mix() -> None:
    # The official cache's layout: every image is its own batch item, so the "spatial"
    # attention is per image and a perturbation of camera 2 cannot reach camera 0.
    teacher, images = small_teacher(), clip(1, 1, 3)
    block = teacher.spatial_blocks[0]
    positions = teacher._positions(2, 3, torch.device("cpu"))
    with torch.no_grad():
        tokens = teacher.tokens(images)[0, 0]  # (V, P, C)
        perturbed = images.clone()
        perturbed[0, 0, 2] += 0.3
        tokens_p = teacher.tokens(perturbed)[0, 0]
        stacked, stacked_p = block(tokens, positions), block(tokens_p, positions)
        joint = block(tokens.reshape(1, -1, 32), positions.repeat(3, 1)).view(3, -1, 32)
        joint_p = block(tokens_p.reshape(1, -1, 32), positions.repeat(3, 1)).view(3, -1, 32)
    assert torch.equal(stacked[0], stacked_p[0])  # no change at all
    assert (joint[0] - joint_p[0]).abs().max() > 1e-4  # the factorized layout does mix
    torch.testing.assert_close(teacher(images).spatial[0][0, 0], joint)


def test_one_camera_one_frame_reduces_to_per_image_attention() -> None:
    teacher = small_teacher()
    images = clip(2, 1, 1)
    out = teacher(images)
    positions = teacher._positions(2, 3, torch.device("cpu"))
    for i in range(2):  # each image alone, block by block
        z = teacher.tokens(images[i : i + 1])[0, 0, 0][None]  # (1, P, C)
        for block in range(2):
            z = teacher.spatial_blocks[block](z, positions)
            torch.testing.assert_close(out.spatial[block][i, 0, 0], z[0])
            z = teacher.temporal_blocks[block](z, positions)
            torch.testing.assert_close(out.temporal[block][i, 0, 0], z[0])


def test_output_shapes_and_any_multiple_of_the_patch_size() -> None:
    teacher = small_teacher(dtype=torch.float32)
    for h, w in [(PATCH, PATCH), (3 * PATCH, 5 * PATCH)]:
        out = teacher(torch.rand(2, 3, 4, 3, h, w))
        grid = (h // PATCH, w // PATCH)
        assert out.patch_grid == grid and out.patch_start_idx == 5
        p = 5 + grid[0] * grid[1]
        assert len(out.spatial) == len(out.temporal) == 2
        for z in [*out.spatial, *out.temporal]:
            assert z.shape == (2, 3, 4, p, 32)


def test_gradients_reach_every_parameter(device: torch.device) -> None:
    teacher = small_teacher(dtype=torch.float32).to(device)
    out = teacher(clip(1, 2, 2, dtype=torch.float32).to(device))
    (out.temporal[-1].square().mean() + out.spatial[-1].mean()).backward()
    for name, parameter in teacher.named_parameters():
        assert parameter.grad is not None and bool(parameter.grad.abs().sum() > 0), name


# ---------------------------------------------------------------------------------------
# rotary embedding
# ---------------------------------------------------------------------------------------


@settings(max_examples=20)
@given(st.integers(0, 2**31 - 1), st.integers(-5, 5), st.integers(-5, 5))
def test_rope_scores_depend_only_on_relative_positions(seed: int, dr: int, dc: int) -> None:
    g = torch.Generator().manual_seed(seed)
    q, k = torch.randn(2, 8, dtype=torch.float64, generator=g)
    pos = torch.randint(0, 10, (2, 2), generator=g)
    shift = torch.tensor([dr, dc])

    def score(positions: torch.Tensor) -> torch.Tensor:
        return (rotary_2d(q[None], positions[:1]) * rotary_2d(k[None], positions[1:])).sum()

    torch.testing.assert_close(score(pos), score(pos + shift))
    norms = rotary_2d(q[None], pos[:1]).norm()
    torch.testing.assert_close(norms, q.norm())


def test_rope_is_the_identity_at_the_origin() -> None:
    x = torch.randn(3, 5, 8)
    assert torch.equal(rotary_2d(x, torch.zeros(5, 2, dtype=torch.long)), x)


# ---------------------------------------------------------------------------------------
# target maps
# ---------------------------------------------------------------------------------------


def test_teacher_output_targets_concatenate_spatial_and_temporal_at_the_reference_time() -> None:
    out = small_teacher()(clip(1, 3, 2))
    features = FactorizedTeacherFeatures(64, 8, layer=0, reference_time=-1).double()
    maps = features.select(out)
    expected = torch.cat([out.spatial[0][:, -1], out.temporal[0][:, -1]], -1)[:, :, 5:]
    expected = expected.unflatten(2, (2, 3)).movedim(-1, 2)
    assert torch.equal(maps, expected)
    targets = features(out, (8, 12))
    assert targets.shape == (1, 2, 8, 8, 12)
    projected = features.project(maps).flatten(0, 1)
    upsampled = F.interpolate(projected, (8, 12), mode="bilinear", align_corners=False)
    torch.testing.assert_close(targets.flatten(0, 1), upsampled)


def vggt_layout(b: int, t: int, v: int, rows: int, cols: int, start: int) -> list[torch.Tensor]:
    """Per-block ``(B, T V, start + rows cols, 8)`` tokens whose patches encode (block, t,
    v, row, col) and whose special tokens are -1."""
    blocks = []
    for block in range(2):
        tokens = torch.full((b, t * v, start + rows * cols, 8), -1.0)
        for s in range(t * v):
            for r in range(rows):
                for c in range(cols):
                    code = torch.tensor([block, s // v, s % v, r, c, 100 + s // v, 0, 0])
                    tokens[:, s, start + r * cols + c] = code
        blocks.append(tokens)
    return blocks


@pytest.mark.parametrize("reference_time", [0, 2, -1])
def test_vggt_layout_is_placed_by_time_camera_and_patch(reference_time: int) -> None:
    b, t, v, rows, cols = 2, 3, 4, 2, 5
    features = FactorizedTeacherFeatures(
        8, 4, layer=1, reference_time=reference_time, patch_start_idx=5
    )
    maps = features.select(
        vggt_layout(b, t, v, rows, cols, 5), patch_grid=(rows, cols), num_cameras=v
    )
    assert maps.shape == (b, v, 8, rows, cols)
    assert bool((maps != -1).all())  # special tokens dropped
    time = reference_time % t
    assert bool((maps[:, :, 0] == 1).all())  # block `layer`
    assert bool((maps[:, :, 1] == time).all())
    for camera in range(v):
        assert bool((maps[:, camera, 2] == camera).all())
    row_index = torch.arange(rows)[:, None].expand(rows, cols)
    col_index = torch.arange(cols)[None].expand(rows, cols)
    assert bool((maps[:, :, 3] == row_index).all())
    assert bool((maps[:, :, 4] == col_index).all())
    assert features(
        vggt_layout(b, t, v, rows, cols, 5), (7, 9), patch_grid=(rows, cols), num_cameras=v
    ).shape == (b, v, 4, 7, 9)


def test_frozen_projector_has_no_parameters_and_is_seeded() -> None:
    a = FactorizedTeacherFeatures(16, 4, seed=1)
    assert list(a.parameters()) == []
    assert torch.equal(a.weight, FactorizedTeacherFeatures(16, 4, seed=1).weight)
    assert not torch.equal(a.weight, FactorizedTeacherFeatures(16, 4, seed=2).weight)
    torch.testing.assert_close(a.weight @ a.weight.T, torch.eye(4))  # orthonormal rows
    trainable = FactorizedTeacherFeatures(16, 4, projector="trainable")
    assert {n for n, _ in trainable.named_parameters()} == {"linear.weight", "linear.bias"}


def fit_constant_student(projector: str) -> float:
    """Fit a constant student map (one learnable C_a vector) to fixed teacher maps."""
    torch.manual_seed(0)
    teacher_maps = torch.randn(2, 3, 16, 4, 6)  # (B, V, 2C, H', W'): varies per pixel
    features = FactorizedTeacherFeatures(16, 4, projector=projector)
    student = torch.nn.Parameter(torch.randn(4))
    optimiser = torch.optim.Adam([student, *features.parameters()], lr=0.05)
    for _ in range(300):
        targets = features.project(teacher_maps)
        constant = student[None, None, :, None, None].expand_as(targets)
        loss = distillation_loss(constant, targets)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        return float(distillation_loss(constant, features.project(teacher_maps)))


@pytest.mark.slow
def test_collapse_a_constant_student_cannot_match_a_frozen_projector_but_can_a_trainable_one() -> (
    None
):
    frozen = fit_constant_student("frozen")
    trainable = fit_constant_student("trainable")
    assert frozen > 0.5  # non-constant targets keep the loss high
    assert trainable < 0.05  # zero weights + bias = the student: the collapsed solution


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------


def test_image_size_not_a_multiple_of_the_patch_size_is_rejected() -> None:
    with pytest.raises(ValueError, match="multiples of patch_size"):
        small_teacher()(torch.rand(1, 1, 1, 3, PATCH + 1, PATCH, dtype=torch.float64))
    with pytest.raises(TypeCheckError, match="images"):
        small_teacher()(torch.rand(1, 1, 3, PATCH, PATCH, dtype=torch.float64))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"embed_dim": 0}, "embed_dim"),
        ({"num_heads": 3}, "num_heads"),
        ({"embed_dim": 24, "num_heads": 4}, "num_heads"),
        ({"patch_size": 0}, "patch_size"),
        ({"depth": 0}, "depth"),
        ({"num_register_tokens": -1}, "num_register_tokens"),
        ({"rope_base": 0.0}, "rope_base"),
    ],
)
def test_bad_teacher_configuration(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        FactorizedSpatioTemporalTeacher(**{"embed_dim": 32, "num_heads": 2, **kwargs})


def test_bad_target_requests() -> None:
    out = small_teacher()(clip(1, 2, 2))
    with pytest.raises(IndexError, match="layer"):
        FactorizedTeacherFeatures(64, layer=5).double()(out, (4, 4))
    with pytest.raises(IndexError, match="reference_time"):
        FactorizedTeacherFeatures(64, reference_time=2).double()(out, (4, 4))
    with pytest.raises(ValueError, match="in_dim"):
        FactorizedTeacherFeatures(32).double()(out, (4, 4))
    with pytest.raises(ValueError, match="output_size"):
        FactorizedTeacherFeatures(64).double()(out, (0, 4))
    blocks = vggt_layout(1, 2, 3, 2, 2, 5)
    with pytest.raises(ValueError, match="patch_grid"):
        FactorizedTeacherFeatures(8, patch_start_idx=5)(blocks, (4, 4))
    with pytest.raises(ValueError, match="num_cameras"):
        FactorizedTeacherFeatures(8, patch_start_idx=5)(
            blocks, (4, 4), patch_grid=(2, 2), num_cameras=4
        )
    with pytest.raises(ValueError, match="tokens per image"):
        FactorizedTeacherFeatures(8, patch_start_idx=4)(
            blocks, (4, 4), patch_grid=(2, 2), num_cameras=3
        )
    with pytest.raises(ValueError, match="projector"):
        FactorizedTeacherFeatures(8, projector="learned")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="out_dim"):
        FactorizedTeacherFeatures(8, 0)
    assert isinstance(out, TeacherOutput)


# ---------------------------------------------------------------------------------------
# empty axes, sizes, dtypes (issue 17)
# ---------------------------------------------------------------------------------------


@settings(max_examples=20)
@given(st.integers(0, 2), st.integers(0, 2), st.integers(0, 2))
def test_empty_clips_give_empty_outputs_of_the_right_shape(b: int, t: int, v: int) -> None:
    teacher = small_teacher(depth=1)
    out = teacher(clip(b, t, v))
    p = out.patch_start_idx + 2 * 3
    for block in (*out.spatial, *out.temporal):
        assert block.shape == (b, t, v, p, 32) and block.dtype == torch.float64
    features = FactorizedTeacherFeatures(64, 8).double()
    if t == 0:
        with pytest.raises(ValueError, match="teacher: holds T = 0 time steps"):
            features(out, (5, 7))
    else:
        maps = features(out, (5, 7))
        assert maps.shape == (b, v, 8, 5, 7)
    # The same clip in VGGT layout: (B, S = T V, P, 2C) per block.
    pairs = zip(out.spatial, out.temporal, strict=True)
    blocks = [torch.cat([s, m], -1).flatten(1, 2) for s, m in pairs]
    vggt = FactorizedTeacherFeatures(64, 8, patch_start_idx=out.patch_start_idx).double()
    if t == 0:
        with pytest.raises(ValueError, match="teacher: holds T = 0 time steps"):
            vggt(blocks, (5, 7), patch_grid=(2, 3), num_cameras=max(v, 1))
    elif v > 0:
        assert vggt(blocks, (5, 7), patch_grid=(2, 3), num_cameras=v).shape == (b, v, 8, 5, 7)


def test_images_smaller_than_a_patch_are_rejected() -> None:
    teacher = small_teacher(depth=1)
    for h, w in [(0, 2 * PATCH), (2 * PATCH, 0), (PATCH - 1, PATCH)]:
        with pytest.raises(ValueError, match=r"images: H and W must be at least patch_size"):
            teacher(torch.rand(1, 1, 1, 3, h, w, dtype=torch.float64))


def test_teacher_outputs_without_blocks_are_rejected() -> None:
    empty = TeacherOutput([], [], 5, (2, 3))
    with pytest.raises(ValueError, match="teacher: holds no blocks"):
        FactorizedTeacherFeatures(64)(empty, (4, 4))
    with pytest.raises(ValueError, match="teacher: holds no blocks"):
        FactorizedTeacherFeatures(64)([], (4, 4), patch_grid=(2, 3), num_cameras=1)
    out = small_teacher(depth=1)(clip(1, 2, 2))
    with pytest.raises(ValueError, match="patch_grid: expected"):
        FactorizedTeacherFeatures(64).double()(
            [torch.cat([out.spatial[0], out.temporal[0]], -1).flatten(1, 2)],
            (4, 4),
            patch_grid=(-2, -3),
            num_cameras=2,
        )


def test_mixed_dtypes_are_type_errors() -> None:
    teacher = small_teacher(depth=1)  # float64 parameters
    with pytest.raises(TypeError, match=r"images: dtype torch.float32 differs from the teacher"):
        teacher(clip(1, 1, 1, dtype=torch.float32))
    out = teacher(clip(1, 2, 2))
    mixed = TeacherOutput(out.spatial, [x.float() for x in out.temporal], 5, out.patch_grid)
    with pytest.raises(TypeError, match=r"teacher: dtype torch.float32 differs"):
        FactorizedTeacherFeatures(64).double()(mixed, (4, 4))
    trainable = FactorizedTeacherFeatures(64, projector="trainable")  # float32 parameters
    with pytest.raises(TypeError, match=r"teacher: dtype torch.float64 differs from the proj"):
        trainable(out, (4, 4))


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_teacher_tokens_are_projected_in_float32(half: torch.dtype) -> None:
    out = small_teacher(depth=1, dtype=torch.float32)(clip(1, 2, 2, dtype=torch.float32))
    features = FactorizedTeacherFeatures(64, 8)
    halved = TeacherOutput(
        [x.to(half) for x in out.spatial], [x.to(half) for x in out.temporal], 5, out.patch_grid
    )
    maps = features(halved, (5, 7))
    assert maps.dtype == half and torch.isfinite(maps).all()
    expected = features(
        TeacherOutput(
            [x.float() for x in halved.spatial],
            [x.float() for x in halved.temporal],
            5,
            out.patch_grid,
        ),
        (5, 7),
    )
    torch.testing.assert_close(maps, expected.to(half), rtol=0, atol=0)


def test_memory_guard_before_attention() -> None:
    teacher = small_teacher(depth=1)
    images = clip(1, 2, 2)
    nbytes, sizes = teacher.memory_estimate(images.shape, 8)
    assert nbytes > 1000 and "B*T*V = 1*2*2" in sizes and "T*P = 22" in sizes
    with (
        dego.memory_limit(1000),
        pytest.raises(ValueError, match=r"FactorizedSpatioTemporalTeacher: .*memory limit"),
    ):
        teacher(images)
    with dego.memory_limit(nbytes):
        teacher(images)  # exactly at the limit: allowed
    # Huge token counts are refused at the default limit without allocating anything.
    big = torch.empty(1, 64, 6, 3, 1, 1, dtype=torch.float64).expand(1, 64, 6, 3, 1400, 1400)
    with pytest.raises(ValueError, match="memory limit"):
        teacher(big)
    # The estimate grows quadratically with the frames attended jointly (T P > V P here).
    small = teacher.memory_estimate((1, 12, 2, 3, 32, 48))[0]
    assert teacher.memory_estimate((1, 24, 2, 3, 32, 48))[0] > 3 * small


def test_memory_guard_on_target_maps() -> None:
    out = small_teacher(depth=1)(clip(1, 2, 2))
    with (
        dego.memory_limit(1000),
        pytest.raises(ValueError, match=r"FactorizedTeacherFeatures: .*memory limit"),
    ):
        FactorizedTeacherFeatures(64, 8).double()(out, (40, 40))
