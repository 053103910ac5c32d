"""The feed-forward miniature: cached scenes, the image network, the variants, the scores."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import dego.demo.feedforward.data as data_module
from dego.demo import MOVABLE_CLASSES, agent_under
from dego.demo.feedforward import (
    FEEDFORWARD_VARIANTS,
    DataConfig,
    GaussianPredictor,
    SceneRecord,
    TrainConfig,
    build_deformation,
    evaluate,
    gaussians_at_frame,
    load_scenes,
    predict,
    scene_seeds,
    score_scenes,
    step_loss,
    train,
)

TINY = DataConfig(train_scenes=2, heldout_scenes=1, image_size=(16, 48))
SMALL_NET = TrainConfig(steps=2, width=4, hidden_dim=8, head_hidden=8, latent_dim=4)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("scenes")


@pytest.fixture(scope="module")
def records(cache: Path) -> list[SceneRecord]:
    return load_scenes(scene_seeds(0, 0, 2), TINY, cache)


# -- data ---------------------------------------------------------------------------------


def test_scene_seeds_are_deterministic_and_split() -> None:
    train_seeds, heldout = scene_seeds(0, 0, 64), scene_seeds(0, 1, 16)
    assert train_seeds == scene_seeds(0, 0, 64) and len(set(train_seeds)) == 64
    assert not set(train_seeds) & set(heldout)
    assert scene_seeds(1, 0, 4) != train_seeds[:4]
    assert scene_seeds(0, 0, 8)[:4] == train_seeds[:4]  # more scenes extend the list
    with pytest.raises(ValueError, match="seed: expected"):
        scene_seeds(-1, 0, 2)


def test_data_config_checks_and_digest() -> None:
    assert DataConfig().digest() == DataConfig().digest()
    assert DataConfig(frames=5).digest() != DataConfig().digest()
    assert DataConfig(image_size=(32, 88)).digest() != DataConfig().digest()
    assert DataConfig(train_scenes=3).digest() == DataConfig().digest()  # not a render setting
    for bad, match in (
        ({"train_scenes": 0}, "train_scenes"),
        ({"frames": 1}, "frames"),
        ({"image_size": (4, 88)}, "image_size"),
        ({"image_size": (8,)}, "image_size"),
        ({"frame_dt": 0.0}, "frame_dt"),
    ):
        with pytest.raises(ValueError, match=match):
            DataConfig(**bad)  # type: ignore[arg-type]


def test_records_hold_what_training_and_scoring_need(records: list[SceneRecord]) -> None:
    record = records[0]
    t, v, h, w = record.depth.shape
    assert (t, h, w) == (3, 16, 48) and record.times.tolist() == [-1.0, 0.0, 1.0]
    assert record.images.shape == (v, 3, h, w) and 0 <= record.images.min() <= 1
    assert record.occupancy.shape == tuple(record.grid.shape)
    assert record.agent_translations.shape == (t, record.agent_labels.shape[0], 3)
    assert torch.equal(
        record.agent_translations[record.reference], torch.zeros_like(record.agent_translations[0])
    )
    clip = record.reference_clip()
    assert clip.num_frames == 1 and clip.reference == 0
    assert torch.equal(clip.occupancy[0], record.occupancy)


def test_the_cache_is_read_back_not_rendered_again(
    records: list[SceneRecord], cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def render(*args: object, **kwargs: object) -> None:
        raise AssertionError("rendered a cached scene again")

    monkeypatch.setattr(data_module, "SyntheticScene", render)
    again = load_scenes(scene_seeds(0, 0, 2), TINY, cache)
    for first, second in zip(records, again, strict=True):
        for field in dataclasses.fields(SceneRecord):
            a, b = getattr(first, field.name), getattr(second, field.name)
            if field.name == "images":  # stored as uint8
                torch.testing.assert_close(a, b, atol=0.5 / 255, rtol=0)
            elif isinstance(a, torch.Tensor):
                assert a.dtype == b.dtype and torch.equal(a, b), field.name
            else:
                assert a == b, field.name


@pytest.mark.parametrize("damage", ["truncated", "garbage", "other seed", "other settings"])
def test_a_bad_cache_file_is_rendered_again_with_a_warning(tmp_path: Path, damage: str) -> None:
    seeds = scene_seeds(5, 0, 2)
    first = load_scenes(seeds[:1], TINY, tmp_path)[0]
    folder = tmp_path / f"scenes-{TINY.digest()}"
    path = folder / f"scene-{seeds[0]}.npz"
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:-200])
    elif damage == "garbage":
        path.write_bytes(b"not a zip at all")
    elif damage == "other seed":
        load_scenes(seeds[1:], TINY, tmp_path)
        path.write_bytes((folder / f"scene-{seeds[1]}.npz").read_bytes())
    else:
        arrays = dict(np.load(path))
        arrays["settings"] = np.frombuffer(b'{"frames": 9}', np.uint8)
        np.savez_compressed(path, **arrays)
    with pytest.warns(UserWarning, match="unusable cached scene"):
        again = load_scenes(seeds[:1], TINY, tmp_path)[0]
    assert torch.equal(again.depth, first.depth) and again.seed == seeds[0]
    load_scenes(seeds[:1], TINY, tmp_path)  # rewritten: no warning now (filterwarnings=error)


def test_a_changed_setting_uses_another_folder(tmp_path: Path) -> None:
    seeds = scene_seeds(0, 0, 1)
    load_scenes(seeds, TINY, tmp_path)
    other = dataclasses.replace(TINY, image_size=(16, 40))
    record = load_scenes(seeds, other, tmp_path)[0]
    assert record.image_size == (16, 40)
    assert len(list(tmp_path.glob("scenes-*"))) == 2


# -- the network --------------------------------------------------------------------------


def test_the_network_puts_one_gaussian_on_each_block_ray(records: list[SceneRecord]) -> None:
    record = records[0]
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    prediction = predict(network, record)
    g = prediction.gaussians
    v = record.images.shape[0]
    assert g.batch_shape == (1,) and g.num_gaussians == v * 2 * 6
    assert prediction.latent.shape == (1, g.num_gaussians, 3)
    assert prediction.logits.shape == (1, g.num_gaussians, 17)
    torch.testing.assert_close(g.features.sum(-1), torch.ones(1, g.num_gaussians))
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(1, g.num_gaussians))
    # project every mean into its own camera: inside its block, at a depth in range
    ref = record.reference
    means = g.means[0].reshape(v, -1, 3)
    cam = torch.einsum("vij,vnj->vni", record.world_to_cam[ref][:, :3, :3], means)
    cam = cam + record.world_to_cam[ref][:, None, :3, 3]
    assert (cam[..., 2] >= 1 - 1e-4).all() and (cam[..., 2] <= 60 + 1e-3).all()
    pixels = torch.einsum("vij,vnj->vni", record.intrinsics[ref], cam)
    pixels = (pixels[..., :2] / pixels[..., 2:]).reshape(v, 2, 6, 2)
    cols, rows = torch.meshgrid(torch.arange(6.0), torch.arange(2.0), indexing="xy")
    assert ((pixels[..., 0] - (cols * 8 + 4)).abs() <= 4 + 1e-3).all()
    assert ((pixels[..., 1] - (rows * 8 + 4)).abs() <= 4 + 1e-3).all()


def test_the_network_refuses_bad_input_and_settings() -> None:
    network = GaussianPredictor(width=4)
    images = torch.rand(1, 2, 3, 16, 16)
    eye = torch.eye(4).expand(1, 2, 4, 4)
    with pytest.raises(ValueError, match="images: expected"):
        network(images[:, :, :2], eye, torch.eye(3).expand(1, 2, 3, 3))
    with pytest.raises(ValueError, match="world_to_cam, intrinsics"):
        network(images, eye[:, :1], torch.eye(3).expand(1, 2, 3, 3))
    for kwargs, match in (
        ({"block": 6}, "block: expected a power of two"),
        ({"block": 1}, "block"),
        ({"depth_range": (5.0, 1.0)}, "depth_range"),
        ({"scale_range": (0.0, 1.0)}, "scale_range"),
    ):
        with pytest.raises(ValueError, match=match):
            GaussianPredictor(**kwargs)  # type: ignore[arg-type]


# -- the variants -------------------------------------------------------------------------


def test_each_variant_carries_the_gaussians_its_own_way(records: list[SceneRecord]) -> None:
    record = records[0]
    torch.manual_seed(0)
    network = GaussianPredictor(width=4, latent_dim=4)
    prediction = predict(network, record)
    other = 0 if record.reference else 1
    canonical = prediction.gaussians
    for variant in ("static", "single-frame"):
        moved, regulariser = gaussians_at_frame(prediction, variant, None, record, other)
        assert moved is canonical and regulariser == 0
    # the oracle: Gaussians on an agent move by its translation, the others stay
    oracle, _ = gaussians_at_frame(prediction, "true-motion", None, record, other)
    agent = agent_under(canonical.means[0], record.reference_clip())
    shift = (oracle.means - canonical.means)[0]
    expected = torch.cat([torch.zeros(1, 3), record.agent_translations[other]])[agent]
    torch.testing.assert_close(shift, expected)
    assert torch.equal(shift[agent == 0], torch.zeros_like(shift[agent == 0]))
    # the networks: only Gaussians of a movable predicted class move (the default gating)
    config = TrainConfig(latent_dim=4)
    deformation = build_deformation("decoupled", config, record.times)
    assert deformation is not None and deformation.fixed_mask is None
    rigid = build_deformation("rigid", config, record.times)
    assert rigid is not None and rigid.fixed_mask == 0.0
    assert build_deformation("static", config, record.times) is None
    with torch.no_grad():
        for parameter in deformation.parameters():  # its heads start at zero motion
            parameter.normal_(0, 0.3)
        prediction.logits[0, :5] = -10
        prediction.logits[0, :5, MOVABLE_CLASSES[0]] = 10
        prediction.logits[0, 5:, MOVABLE_CLASSES[0]] = -10
    moved, regulariser = gaussians_at_frame(prediction, "decoupled", deformation, record, other)
    fixed = ~torch.isin(prediction.logits[0].argmax(-1), torch.tensor(MOVABLE_CLASSES))
    assert torch.equal(moved.means[0, fixed], canonical.means[0, fixed])
    assert not torch.equal(moved.means[0, :5], canonical.means[0, :5])
    assert regulariser.ndim == 0 and regulariser.requires_grad


def test_training_is_seeded_and_every_variant_learns_something(
    records: list[SceneRecord],
) -> None:
    for variant in FEEDFORWARD_VARIANTS:
        result = train(records, variant, SMALL_NET)
        assert len(result.history) == 2 and all(math.isfinite(v) for v in result.history)
        assert (result.deformation is None) == (variant not in ("rigid", "decoupled"))
    again = train(records, "decoupled", SMALL_NET)
    assert again.history == train(records, "decoupled", SMALL_NET).history
    # one step moves the network's weights
    before = train(records, "static", dataclasses.replace(SMALL_NET, steps=0)).network
    after = train(records, "static", dataclasses.replace(SMALL_NET, steps=1)).network
    assert any(
        not torch.equal(a, b) for a, b in zip(before.parameters(), after.parameters(), strict=True)
    )


def test_single_frame_renders_the_reference_only(
    records: list[SceneRecord], monkeypatch: pytest.MonkeyPatch
) -> None:
    import dego.demo.feedforward.training as train_module

    seen: list[int] = []
    original = train_module.gaussians_at_frame

    def spy(prediction, variant, deformation, record, index, deform="movable"):  # type: ignore[no-untyped-def]
        seen.append(index)
        return original(prediction, variant, deformation, record, index, deform)

    monkeypatch.setattr(train_module, "gaussians_at_frame", spy)
    network = GaussianPredictor(width=4, latent_dim=4)
    generator = torch.Generator().manual_seed(0)
    for _ in range(3):
        step_loss(network, None, records[0], "single-frame", SMALL_NET, generator)
    assert set(seen) == {records[0].reference}
    seen.clear()
    for _ in range(6):
        step_loss(network, None, records[0], "static", SMALL_NET, generator)
    assert seen.count(records[0].reference) == 6 and len(set(seen)) == 3


def test_train_config_and_train_refuse_bad_values(records: list[SceneRecord]) -> None:
    for kwargs, match in (
        ({"steps": -1}, "steps"),
        ({"lr": 0.0}, "lr"),
        ({"cameras_per_step": 0}, "cameras_per_step"),
        ({"block": 12}, "block"),
        ({"deform": "some"}, "deform"),
        ({"depth_weight": math.nan}, "depth_weight"),
        ({"seed": -1}, "seed"),
    ):
        with pytest.raises(ValueError, match=match):
            TrainConfig(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="records"):
        train([], "static", SMALL_NET)
    with pytest.raises(ValueError, match="variant"):
        train(records, "free-offsets", SMALL_NET)  # type: ignore[arg-type]


# -- scoring ------------------------------------------------------------------------------


@pytest.mark.slow
def test_ground_truth_scores_100_and_nothing_scores_0(records: list[SceneRecord]) -> None:
    perfect = score_scenes([r.occupancy for r in records], records)
    for name in ("IoU", "mIoU", "RayIoU"):
        assert perfect[name] == pytest.approx(100.0), name
    empty = score_scenes([torch.full_like(r.occupancy, 17) for r in records], records)
    assert empty["IoU"] == 0 and empty["mIoU"] == 0
    with pytest.raises(ValueError, match="labels: expected one grid per scene"):
        score_scenes([records[0].occupancy], records)
    scores = evaluate(GaussianPredictor(width=4), records[:1])
    assert set(scores) == {
        "IoU", "mIoU", "InsM", "ScnM", "HCM", "RayIoU", "vehicles", "articulated"
    }  # fmt: skip
