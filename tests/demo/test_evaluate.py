"""4D evaluation of the demo: frames in their own ego coordinates, moving-agent regions,
the lifted-labels ceiling, the static variant and the class-balanced initialisation."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dego import (
    GaussianSet,
    SyntheticScene,
    quaternions_to_rotation_matrices,
    rotation_matrices_to_quaternions,
)
from dego.demo import (
    DYNAMIC_GROUPS,
    MOVABLE_CLASSES,
    OFFSET_GROUPS,
    DemoClip,
    DynamicCounts,
    FitConfig,
    GaussianSceneModel,
    dynamic_counts,
    dynamic_regions,
    fit_scene,
    gaussians_at,
    lift_labels,
    offset_group,
    predict_clip,
    predict_labels,
    rigidity_mask,
    score_clip,
    to_ego,
)


@pytest.fixture(scope="module")
def clip() -> DemoClip:
    return DemoClip.from_scene(SyntheticScene(1, num_frames=3))


# -- rigid motions of Gaussian sets ---------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000))
def test_rotation_matrices_to_quaternions_round_trips(seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    quats = torch.randn(64, 4, generator=g, dtype=torch.float64)
    rotations = quaternions_to_rotation_matrices(quats)
    back = rotation_matrices_to_quaternions(rotations)
    assert (back[:, 0] >= 0).all()
    torch.testing.assert_close(torch.linalg.vector_norm(back, dim=-1), torch.ones(64).double())
    torch.testing.assert_close(quaternions_to_rotation_matrices(back), rotations)


def test_rotation_matrices_to_quaternions_at_half_turns() -> None:
    # trace = -1: the w-based formula alone would divide by ~0
    for axis in torch.eye(3, dtype=torch.float64):
        quat = torch.cat([torch.zeros(1, dtype=torch.float64), axis])
        rotation = quaternions_to_rotation_matrices(quat)
        back = rotation_matrices_to_quaternions(rotation)
        torch.testing.assert_close(quaternions_to_rotation_matrices(back), rotation)


def random_set(seed: int, batch: tuple[int, ...] = (2,), n: int = 7) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    return GaussianSet(
        means=torch.randn(*batch, n, 3, generator=g, dtype=torch.float64),
        quats=torch.randn(*batch, n, 4, generator=g, dtype=torch.float64),
        scales=torch.rand(*batch, n, 3, generator=g, dtype=torch.float64) + 0.1,
        opacities=torch.rand(*batch, n, generator=g, dtype=torch.float64),
        features=torch.randn(*batch, n, 5, generator=g, dtype=torch.float64),
    )


def rigid_matrix(seed: int, batch: tuple[int, ...] = ()) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 1)
    matrix = torch.eye(4, dtype=torch.float64).repeat(*batch, 1, 1)
    matrix[..., :3, :3] = quaternions_to_rotation_matrices(
        torch.randn(*batch, 4, generator=g, dtype=torch.float64)
    )
    matrix[..., :3, 3] = 5 * torch.randn(*batch, 3, generator=g, dtype=torch.float64)
    return matrix


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.booleans())
def test_transformed_moves_means_and_rotates_covariances(seed: int, per_item: bool) -> None:
    gaussians = random_set(seed)
    matrix = rigid_matrix(seed, (2,) if per_item else ())
    moved = gaussians.transformed(matrix)
    rotation = matrix[..., None, :3, :3] if per_item else matrix[:3, :3]
    translation = matrix[..., None, :3, 3] if per_item else matrix[:3, 3]
    expected_means = (rotation @ gaussians.means.unsqueeze(-1)).squeeze(-1) + translation
    torch.testing.assert_close(moved.means, expected_means)
    expected_cov = rotation @ gaussians.covariances() @ rotation.transpose(-1, -2)
    torch.testing.assert_close(moved.covariances(), expected_cov)
    for name in ("scales", "opacities", "features"):
        assert torch.equal(getattr(moved, name), getattr(gaussians, name))
    back = moved.transformed(torch.linalg.inv(matrix))  # the inverse motion undoes it
    torch.testing.assert_close(back.means, gaussians.means)
    torch.testing.assert_close(back.covariances(), gaussians.covariances())


def test_transformed_rejects_a_mismatched_batch_and_non_rigid_matrices() -> None:
    with pytest.raises(ValueError, match="matrix"):
        random_set(0).transformed(torch.eye(4, dtype=torch.float64).repeat(3, 1, 1))
    scaled, mirrored, broken = (torch.eye(4, dtype=torch.float64) for _ in range(3))
    scaled[0, 0] = 2.0
    mirrored[1, 1] = -1.0
    broken[0, 3] = float("nan")
    for matrix in (scaled, mirrored, broken):
        with pytest.raises(ValueError, match="rigid"):
            random_set(0).transformed(matrix)


def test_transformed_is_differentiable() -> None:
    gaussians = random_set(0)
    means = gaussians.means.clone().requires_grad_(True)
    moved = gaussians.replace(means=means).transformed(rigid_matrix(0))
    moved.means.sum().backward()
    assert means.grad is not None and torch.isfinite(means.grad).all()


# -- the clip in 4D -------------------------------------------------------------------------


@pytest.mark.slow
def test_clip_keeps_every_frame(clip: DemoClip) -> None:
    t = clip.num_frames
    assert clip.occupancy.shape == clip.mask_camera.shape == clip.instances.shape
    assert clip.occupancy.shape == (t, *clip.grid.shape)
    assert clip.instance_pixels.shape == clip.depth.shape
    assert clip.ego_poses.shape == (t, 4, 4)
    torch.testing.assert_close(clip.ego_poses[clip.reference], torch.eye(4))
    a = clip.agent_labels.shape[0]
    assert clip.agent_articulated.shape == clip.agent_moving.shape == (a,)
    assert int(clip.instances.max()) <= a and int(clip.instance_pixels.max()) <= a
    # the ego moves, so frames differ
    assert not torch.equal(clip.occupancy[0], clip.occupancy[-1])
    agents = clip.instances > 0
    assert torch.equal(clip.occupancy[agents], clip.agent_labels[(clip.instances[agents] - 1)])


def test_to_ego_at_the_reference_frame_is_the_identity(clip: DemoClip) -> None:
    gaussians = random_set(3, (1,)).to(torch.float32)
    same = to_ego(gaussians, clip, clip.reference)
    torch.testing.assert_close(same.means, gaussians.means)
    later = to_ego(gaussians, clip, clip.num_frames - 1)
    shift = clip.ego_poses[-1, :3, 3]  # the ego drives along +x: points move back
    torch.testing.assert_close(later.means, gaussians.means - shift)


def test_dynamic_regions_cover_the_moving_agents(clip: DemoClip) -> None:
    for index in range(clip.num_frames):
        regions = dynamic_regions(clip, index)
        assert set(regions) == set(DYNAMIC_GROUPS)
        ids = clip.instances[index]
        agent = (ids - 1).clamp_min(0)
        moving = (ids > 0) & clip.agent_moving[agent]
        for name, region in regions.items():
            assert not (region & ~clip.mask_camera[index]).any()
            articulated = clip.agent_articulated[agent]
            members = moving & (articulated if name == "articulated" else ~articulated)
            assert (region | ~(members & clip.mask_camera[index])).all()
            labels = clip.occupancy[index][members]
            assert torch.isin(labels, torch.tensor(DYNAMIC_GROUPS[name])).all()
    assert dynamic_regions(clip, clip.reference)["articulated"].any()


@pytest.mark.slow
def test_ground_truth_scores_perfectly_and_empty_scores_zero(clip: DemoClip) -> None:
    score = score_clip(clip.occupancy, clip)
    row = score.row()
    for column in ("IoU", "mIoU", "mIoU t=±1", "HCM t=±1", "vehicles t=±1", "articulated t=±1"):
        assert row[column] == pytest.approx(100.0), column
    for index in range(clip.num_frames):
        for counts in dynamic_counts(clip.occupancy[index], clip, index).values():
            assert counts.intersection == counts.target == counts.predicted
    assert math.isnan(row["mIoU t=±2+"]) and math.isnan(row["articulated t=±2+"])  # 3 frames
    empty = torch.full_like(clip.occupancy, 17)
    row = score_clip(empty, clip).row()
    assert row["mIoU"] == 0 and row["articulated t=±1"] == 0 and row["vehicles t=±1"] == 0
    with pytest.raises(ValueError, match="labels"):
        score_clip(clip.occupancy[:1], clip)


def test_offset_groups_split_one_frame_from_two_or_more() -> None:
    assert OFFSET_GROUPS == ("t=±1", "t=±2+")
    assert [offset_group(t) for t in (-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 5.0)] == [
        "t=±2+",
        "t=±2+",
        "t=±1",
        None,
        "t=±1",
        "t=±2+",
        "t=±2+",
    ]


@pytest.mark.slow
def test_frames_two_away_are_scored_apart(clip: DemoClip) -> None:
    """Relabel the 3-frame clip's offsets as -2, 0, +2: the ground truth scores 100 in the
    t=±2+ columns and the t=±1 columns are empty (NaN)."""
    far = dataclasses.replace(clip, times=clip.times * 2)
    row = score_clip(far.occupancy, far).row()
    for metric in ("mIoU", "HCM", "vehicles", "articulated"):
        assert row[f"{metric} t=±2+"] == pytest.approx(100.0), metric
        assert math.isnan(row[f"{metric} t=±1"]), metric


def test_dynamic_counts_add_and_iou() -> None:
    total = DynamicCounts(2, 4, 3) + DynamicCounts(1, 1, 2)
    assert total == DynamicCounts(3, 5, 5)
    assert total.iou == pytest.approx(3 / 7)
    assert math.isnan(DynamicCounts().iou)


@pytest.mark.slow
def test_lifted_labels_are_a_high_ceiling(clip: DemoClip) -> None:
    lifted = lift_labels(clip, clip.reference)
    assert lifted.batch_shape == (1,)
    torch.testing.assert_close(lifted.features.sum(-1), torch.ones(1, lifted.num_gaussians))
    assert (lifted.scales == 0.1).all() and (lifted.opacities == 1).all()
    labels = torch.stack(
        [predict_labels(lift_labels(clip, i), clip) for i in range(clip.num_frames)]
    )
    row = score_clip(labels, clip).row()
    assert row["mIoU"] > 40 and row["mIoU t=±1"] > 40 and row["articulated t=±1"] > 30


# -- variants and initialisation --------------------------------------------------------------


@pytest.mark.slow
def test_static_variant_has_no_deformation(clip: DemoClip) -> None:
    result = fit_scene(clip, "static", FitConfig(iterations=2, num_gaussians=300))
    assert result.deformation is None
    assert torch.equal(rigidity_mask(result), torch.zeros(300))
    assert all(v == 0 for v in result.history["deformation"])
    for index in range(clip.num_frames):
        gaussians, losses = gaussians_at(result.model, None, clip, index)
        assert losses is None and torch.equal(gaussians.means, result.model.means[None])
    labels = predict_clip(result.model, None, clip)
    assert labels.shape == (clip.num_frames, *clip.grid.shape)
    last = clip.num_frames - 1
    expected = predict_labels(to_ego(result.model.gaussians(), clip, last), clip)
    assert torch.equal(labels[last], expected)


def test_mask_sparsity_adds_a_term_to_the_decoupled_loss(clip: DemoClip) -> None:
    config = FitConfig(iterations=1, num_gaussians=200, mask_sparsity=0.5)
    result = fit_scene(clip, "decoupled", config)
    other = 0 if clip.reference else 1
    _, plain = gaussians_at(result.model, result.deformation, clip, other)
    _, prior = gaussians_at(result.model, result.deformation, clip, other, mask_sparsity=0.5)
    assert plain is not None and prior is not None and "sparsity" not in plain
    from dego.demo import deformable

    # gated Gaussians (not movable) have m = 0 (DeformationOutput.gated)
    mask = torch.where(deformable(result.model)[0], rigidity_mask(result), 0.0)
    assert float(prior["sparsity"].detach()) == pytest.approx(float(mask.mean()), rel=1e-5)
    expected = float(plain["total"].detach()) + 0.5 * float(mask.mean())
    assert float(prior["total"].detach()) == pytest.approx(expected)
    rigid = fit_scene(clip, "rigid", config)  # a fixed mask has no prior
    _, terms = gaussians_at(rigid.model, rigid.deformation, clip, other, mask_sparsity=0.5)
    assert terms is not None and "sparsity" not in terms


def initial_classes(model: GaussianSceneModel) -> torch.Tensor:
    return model.semantic_logits.argmax(-1)


def test_class_balanced_allocation_gives_small_classes_more_gaussians(clip: DemoClip) -> None:
    def draw(allocation: str) -> GaussianSceneModel:
        return GaussianSceneModel.from_clip(
            clip, 2000, allocation=allocation, generator=torch.Generator().manual_seed(0)
        )

    balanced, area = draw("class_balanced"), draw("area")
    people = torch.tensor([2, 6, 7])
    on_people = torch.isin(initial_classes(balanced), people).sum()
    assert on_people > 4 * torch.isin(initial_classes(area), people).sum()
    assert on_people > 60
    # movable classes come from the reference frame only: they lie on its pseudo surfaces
    movable = torch.isin(initial_classes(balanced), torch.tensor(MOVABLE_CLASSES))
    camera = clip.world_to_cam[clip.reference]
    points = balanced.means.detach()[movable]
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], -1)
    depth_in_cameras = torch.einsum("vij,nj->vni", camera, homogeneous)[..., 2]
    assert (depth_in_cameras > 0).any(0).all()


@pytest.mark.parametrize("prior", [0.0, 0.5, 0.9])
def test_semantic_prior_sets_the_initial_class_probabilities(clip: DemoClip, prior: float) -> None:
    model = GaussianSceneModel.from_clip(
        clip, 500, semantic_prior=prior, generator=torch.Generator().manual_seed(0)
    )
    probabilities = torch.softmax(model.semantic_logits.detach(), -1)
    top = probabilities.max(-1).values
    assert top.mean() == pytest.approx(prior + (1 - prior) / 17, abs=0.02)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"allocation": "uniform"}, "allocation"),
        ({"semantic_prior": 1.0}, "semantic_prior"),
        ({"semantic_prior": -0.1}, "semantic_prior"),
    ],
)
def test_bad_initialisation_arguments(clip: DemoClip, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        GaussianSceneModel.from_clip(clip, 10, **kwargs)
    with pytest.raises(ValueError, match=message):
        FitConfig(**kwargs)


@pytest.mark.parametrize(("field", "value"), [("cameras_per_step", 0), ("mask_sparsity", -1.0)])
def test_fit_config_rejects_bad_new_fields(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        FitConfig(**{field: value})  # type: ignore[arg-type]
