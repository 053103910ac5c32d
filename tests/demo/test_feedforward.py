"""The feed-forward miniature: cached scenes, the image network, the variants, the scores."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import dego.demo.feedforward.data as data_module
import dego.demo.feedforward.training as train_module
from dego.classes import FREE_LABEL, HUMAN_CENTRIC_CLASSES
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
from dego.demo.feedforward.data import FEEDFORWARD_FRAME_DT, MAX_CLIP_SECONDS
from dego.demo.feedforward.evaluate import (
    PEOPLE_SCORES,
    SCORES,
    PeopleCounts,
    people_counts,
    predict_scene,
)
from dego.demo.feedforward.network import SCALE_FLOOR, Prediction
from dego.demo.feedforward.training import (
    DEFORMED_VARIANTS,
    build_network,
    fine_tune,
    median_frequency_weights,
    warm_up,
)
from tests.helpers.feedforward import render_tiny

TINY = DataConfig(train_scenes=2, heldout_scenes=1, image_size=(16, 48))
SMALL_NET = TrainConfig(steps=2, warmup_steps=1, width=4, hidden_dim=8, head_hidden=8, latent_dim=4)


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
    assert DataConfig().frame_dt == FEEDFORWARD_FRAME_DT == 0.5 and MAX_CLIP_SECONDS == 8.0
    assert DataConfig(frames=5).digest() != DataConfig().digest()
    assert DataConfig(image_size=(32, 88)).digest() != DataConfig().digest()
    assert DataConfig(frame_dt=0.2).digest() != DataConfig().digest()
    assert DataConfig(depth_noise=0.1).digest() != DataConfig().digest()
    assert DataConfig(depth_noise=0.1).digest() != DataConfig(depth_noise=0.2).digest()
    assert DataConfig(train_scenes=3).digest() == DataConfig().digest()  # not a render setting
    # the outermost frame may be MAX_CLIP_SECONDS from the reference, not further
    assert DataConfig(frames=33, frame_dt=0.5).frames == 33
    assert DataConfig(frames=3, frame_dt=MAX_CLIP_SECONDS).frames == 3
    assert DataConfig(frames=81, frame_dt=0.2).frames == 81  # the demo's spacing
    assert DataConfig(depth_noise=0.99).depth_noise == 0.99
    for bad, match in (
        ({"train_scenes": 0}, "train_scenes"),
        ({"frames": 1}, "frames"),
        ({"frames": 2}, "frames"),
        ({"frames": 4}, "frames: expected an odd number"),
        ({"frames": 6}, "frames: expected an odd number"),
        ({"image_size": (4, 88)}, "image_size"),
        ({"image_size": (8,)}, "image_size"),
        ({"frame_dt": 0.0}, "frame_dt"),
        ({"frame_dt": -0.5}, "frame_dt"),
        ({"frame_dt": math.nan}, "frame_dt"),
        ({"frames": 35, "frame_dt": 0.5}, "^frame_dt:"),
        ({"frames": 3, "frame_dt": 8.5}, "^frame_dt:"),
        ({"frames": 83, "frame_dt": 0.2}, "^frame_dt:"),
        ({"depth_noise": -0.1}, "depth_noise"),
        ({"depth_noise": 1.0}, "depth_noise"),
        ({"depth_noise": math.nan}, "depth_noise"),
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


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("seed", "two values"),
        ("seed", np.inf),
        ("seed", np.nan),
        ("reference", "two values"),
        ("reference", np.inf),
    ],
)
def test_a_cached_scene_with_a_malformed_scalar_is_rendered_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, value: object
) -> None:
    """A ``seed`` or ``reference`` of shape (2,), or a float such as inf, is an unusable
    cached scene (a warning, rendered again), not a TypeError / OverflowError traceback."""
    rendered = render_tiny(monkeypatch)
    load_scenes([7], TINY, tmp_path)
    path = tmp_path / f"scenes-{TINY.digest()}" / "scene-7.npz"
    arrays = dict(np.load(path))
    arrays[name] = np.array([7, 7]) if value == "two values" else np.array(value)
    np.savez_compressed(path, **arrays)
    with pytest.warns(UserWarning, match=f"unusable cached scene \\({name}: expected one integer"):
        record = load_scenes([7], TINY, tmp_path)[0]
    assert record.seed == 7 and rendered == [7, 7]
    assert load_scenes([7], TINY, tmp_path)[0].seed == 7 and rendered == [7, 7]  # rewritten


def test_a_changed_setting_uses_another_folder(tmp_path: Path) -> None:
    seeds = scene_seeds(0, 0, 1)
    load_scenes(seeds, TINY, tmp_path)
    other = dataclasses.replace(TINY, image_size=(16, 40))
    record = load_scenes(seeds, other, tmp_path)[0]
    assert record.image_size == (16, 40)
    assert len(list(tmp_path.glob("scenes-*"))) == 2


def test_depth_noise_reaches_the_scene(monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[dict] = []

    class StopError(Exception):
        pass

    def scene(seed: int, **kwargs: object) -> None:
        made.append(kwargs)
        raise StopError

    monkeypatch.setattr(data_module, "SyntheticScene", scene)
    config = dataclasses.replace(TINY, depth_noise=0.25, frames=5, frame_dt=0.2)
    with pytest.raises(StopError):
        load_scenes([1], config, None)
    assert made[0]["depth_noise"] == 0.25
    assert made[0]["num_frames"] == 5 and made[0]["frame_dt"] == 0.2


# -- the network --------------------------------------------------------------------------


def test_the_network_puts_one_gaussian_on_each_block_ray(records: list[SceneRecord]) -> None:
    record = records[0]
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    prediction = predict(network, record, "learned")  # anchored depths may leave the range
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


def camera_depths(record: SceneRecord, prediction: Prediction) -> torch.Tensor:
    """``(V, n)`` z-depth of every Gaussian in its own camera (the reference frame's)."""
    ref, v = record.reference, record.images.shape[0]
    means = prediction.gaussians.means[0].reshape(v, -1, 3)
    cam = torch.einsum("vij,vnj->vni", record.world_to_cam[ref][:, :3, :3], means)
    return (cam + record.world_to_cam[ref][:, None, :3, 3])[..., 2]


def forward(
    network: GaussianPredictor, record: SceneRecord, anchor: torch.Tensor | None
) -> Prediction:
    ref = record.reference
    return network(
        record.images[None],
        record.world_to_cam[ref][None],
        record.intrinsics[ref][None],
        anchor_depth=None if anchor is None else anchor[None],
    )


def test_an_anchor_depth_sets_every_gaussians_depth(records: list[SceneRecord]) -> None:
    record = records[0]
    torch.manual_seed(0)
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    anchor = torch.full_like(record.depth[record.reference], 7.0)
    z = camera_depths(record, forward(network, record, anchor))
    torch.testing.assert_close(z, torch.full_like(z, 7.0), atol=1e-4, rtol=0)
    # 0 in camera 2: that camera keeps the network's own depths, the others are anchored
    anchor[2] = 0
    anchored = forward(network, record, anchor)
    free = forward(network, record, None)
    z, z_free = camera_depths(record, anchored), camera_depths(record, free)
    torch.testing.assert_close(z[2], z_free[2])
    assert not torch.allclose(z_free[2], torch.full_like(z_free[2], 7.0), atol=1e-2)
    others = [0, 1, 3, 4, 5]
    torch.testing.assert_close(z[others], torch.full_like(z[others], 7.0), atol=1e-4, rtol=0)
    # only the depth changes: the other parameters are the network's
    for name in ("quats", "scales", "opacities", "features"):
        assert torch.equal(getattr(anchored.gaussians, name), getattr(free.gaussians, name)), name
    assert torch.equal(anchored.logits, free.logits) and torch.equal(anchored.latent, free.latent)


def test_the_anchor_is_read_at_each_gaussians_own_pixel(records: list[SceneRecord]) -> None:
    """A map constant on each 8 x 8 block, another value per block and camera: a Gaussian
    (inside its block) gets its own block's value."""
    record = records[0]
    torch.manual_seed(1)
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    v, h, w = record.depth.shape[1:]
    rows = torch.arange(h)[:, None] // 8
    cols = torch.arange(w)[None, :] // 8
    camera = torch.arange(v)[:, None, None]
    anchor = (2.0 + cols + 6 * rows + 12 * camera).float()  # (V, H, W), every value > 0
    z = camera_depths(record, forward(network, record, anchor))
    expected = anchor[:, ::8, ::8].reshape(v, -1)  # one value per block, row-major
    torch.testing.assert_close(z, expected, atol=1e-3, rtol=1e-5)


def test_predict_anchors_on_the_reference_depth_unless_learned(
    records: list[SceneRecord],
) -> None:
    record = records[0]
    torch.manual_seed(0)
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    anchored = predict(network, record)
    assert torch.equal(
        predict(network, record, "anchored").gaussians.means, anchored.gaussians.means
    )
    reference = forward(network, record, record.depth[record.reference])
    assert torch.equal(anchored.gaussians.means, reference.gaussians.means)
    learned = predict(network, record, "learned")
    assert torch.equal(learned.gaussians.means, forward(network, record, None).gaussians.means)
    assert not torch.allclose(learned.gaussians.means, anchored.gaussians.means)
    with pytest.raises(ValueError, match="depth_source"):
        predict(network, record, "metric")  # type: ignore[arg-type]


def test_scales_stay_above_the_floor(records: list[SceneRecord]) -> None:
    record = records[0]
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    assert network.scale_range == (SCALE_FLOOR, 1.0) and SCALE_FLOOR == 0.1
    assert build_network(SMALL_NET).scale_range == (SMALL_NET.scale_floor, 1.0)
    with torch.no_grad():  # push the scale logits far down: the floor itself
        head = network.head[-1]
        assert head.bias is not None
        head.bias[3:6] = -1e4
    scales = predict(network, record).gaussians.scales
    assert (scales >= SCALE_FLOOR).all()
    torch.testing.assert_close(scales, torch.full_like(scales, SCALE_FLOOR))
    floored = GaussianPredictor(block=8, width=4, scale_range=(0.3, 1.0))
    assert (predict(floored, record).gaussians.scales >= 0.3).all()


def test_a_misshaped_anchor_is_refused(records: list[SceneRecord]) -> None:
    record = records[0]
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    depth = record.depth[record.reference]
    for anchor in (depth[:-1], depth[:, :-1], depth[None], depth[..., :8]):
        with pytest.raises(ValueError, match="anchor_depth"):
            forward(network, record, anchor)


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
        assert (result.deformation is None) == (variant not in DEFORMED_VARIANTS)
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


def test_train_config_new_fields_refuse_bad_values() -> None:
    config = TrainConfig()
    assert (config.steps, config.warmup_steps, config.recipe) == (100, 400, "paired")
    assert config.depth_source == "anchored" and config.scale_floor == SCALE_FLOOR
    assert config.total_steps == 500 and SMALL_NET.total_steps == 3
    assert DEFORMED_VARIANTS == ("rigid", "decoupled", "velocity")
    assert "velocity" in FEEDFORWARD_VARIANTS
    for kwargs, match in (
        ({"recipe": "both"}, "recipe"),
        ({"depth_source": "metric"}, "depth_source"),
        ({"scale_floor": 0.0}, "scale_floor"),
        ({"scale_floor": -0.1}, "scale_floor"),
        ({"scale_floor": 1.0}, "scale_floor"),
        ({"scale_floor": 1.5}, "scale_floor"),
        ({"scale_floor": math.nan}, "scale_floor"),
        ({"clip_norm": -1.0}, "clip_norm"),
        ({"clip_norm": math.inf}, "clip_norm"),
        ({"warmup_steps": -1}, "warmup_steps"),
        ({"finetune_lr": 0.0}, "finetune_lr"),
    ):
        with pytest.raises(ValueError, match=match):
            TrainConfig(**kwargs)  # type: ignore[arg-type]


def test_the_velocity_variant_builds_a_velocity_deformation(records: list[SceneRecord]) -> None:
    deformation = build_deformation("velocity", SMALL_NET, records[0].times)
    assert deformation is not None
    assert deformation.rigid_motion == "velocity" and deformation.fixed_mask is None
    assert deformation.preset == "paper" and deformation.velocity_head is not None
    for variant in ("rigid", "decoupled"):
        other = build_deformation(variant, SMALL_NET, records[0].times)  # type: ignore[arg-type]
        assert other is not None and other.rigid_motion == "time"


def test_fine_tune_leaves_its_start_alone_and_is_seeded(records: list[SceneRecord]) -> None:
    torch.manual_seed(3)
    start = build_network(SMALL_NET)
    before = copy.deepcopy(start.state_dict())
    first = fine_tune(start, records, "velocity", SMALL_NET)
    for name, value in start.state_dict().items():
        assert torch.equal(value, before[name]), name
    assert first.network is not start and len(first.history) == SMALL_NET.steps
    assert any(
        not torch.equal(a, b)
        for a, b in zip(first.network.parameters(), start.parameters(), strict=True)
    )
    second = fine_tune(start, records, "velocity", SMALL_NET)
    assert first.history == second.history
    for a, b in zip(first.network.parameters(), second.network.parameters(), strict=True):
        assert torch.equal(a, b)


def test_warm_up_trains_the_single_frame_start(records: list[SceneRecord]) -> None:
    config = dataclasses.replace(SMALL_NET, warmup_steps=2)
    warm = warm_up(records, config)
    assert warm.variant == "single-frame" and warm.deformation is None
    assert len(warm.history) == 2 and all(math.isfinite(v) for v in warm.history)
    assert warm.history == warm_up(records, config).history
    # train() without a start runs the same warm-up first: the same fine-tuned result
    fine = fine_tune(warm.network, records, "static", config)
    assert train(records, "static", config).history == fine.history


def test_every_variant_sees_the_same_scenes_frames_and_cameras(
    records: list[SceneRecord], monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[tuple[int, bytes]] = []
    original = train_module.step_loss

    def spy(network, deformation, record, variant, config, generator, class_weights=None):  # type: ignore[no-untyped-def]
        seen.append((record.seed, bytes(generator.get_state().numpy())))
        return original(network, deformation, record, variant, config, generator, class_weights)

    monkeypatch.setattr(train_module, "step_loss", spy)
    config = dataclasses.replace(SMALL_NET, steps=5)
    start = build_network(config)
    orders = {}
    for variant in ("single-frame", "static", "velocity"):
        seen.clear()
        fine_tune(start, records, variant, config)  # type: ignore[arg-type]
        orders[variant] = list(seen)
    assert orders["single-frame"] == orders["static"] == orders["velocity"]
    seeds = [seed for seed, _ in orders["static"]]
    assert len(seeds) == 5 and set(seeds) == {r.seed for r in records}
    # and the generator state before each step: the same frames and cameras were drawn
    assert len({state for _, state in orders["static"]}) == 5


def test_the_scratch_recipe_trains_from_the_initial_weights(records: list[SceneRecord]) -> None:
    config = dataclasses.replace(SMALL_NET, recipe="scratch")
    with pytest.raises(ValueError, match="start"):
        train(records, "static", config, start=build_network(config))
    result = train(records, "velocity", config)
    assert len(result.history) == config.total_steps == 3
    assert all(math.isfinite(v) for v in result.history)
    assert result.deformation is not None and result.deformation.rigid_motion == "velocity"
    assert train(records, "velocity", config).history == result.history


def test_cosine_clipping_and_class_weights_still_train(records: list[SceneRecord]) -> None:
    config = dataclasses.replace(
        SMALL_NET, cosine=True, clip_norm=1.0, class_weights=True, depth_source="learned"
    )
    result = train(records, "velocity", config)
    assert len(result.history) == 2 and all(math.isfinite(v) for v in result.history)
    plain = train(records, "velocity", dataclasses.replace(SMALL_NET, depth_source="learned"))
    assert plain.history != result.history


def labelled(record: SceneRecord, counts: dict[int, int], unsupervised: int) -> SceneRecord:
    """``record`` with ``counts[label]`` supervised pixels of each label and the rest
    ``unsupervised`` (not supervised)."""
    semantics = torch.full_like(record.semantics, unsupervised).flatten()
    supervised = torch.zeros_like(record.supervised).flatten()
    start = 0
    for label, count in counts.items():
        semantics[start : start + count] = label
        supervised[start : start + count] = True
        start += count
    return dataclasses.replace(
        record,
        semantics=semantics.reshape(record.semantics.shape),
        supervised=supervised.reshape(record.supervised.shape),
    )


def test_median_frequency_weights(records: list[SceneRecord]) -> None:
    # pooled over the records: label 0 100 pixels, 4 200, 11 400; 5 only where unsupervised
    fakes = [
        labelled(records[0], {0: 60, 4: 200}, unsupervised=5),
        labelled(records[1], {0: 40, 11: 400}, unsupervised=5),
    ]
    weights = median_frequency_weights(fakes)
    assert weights.shape == (FREE_LABEL + 1,) == (18,)
    assert torch.isfinite(weights).all() and (weights > 0).all()
    torch.testing.assert_close(weights[4], torch.tensor(1.0))  # the median frequency
    torch.testing.assert_close(weights[0], torch.tensor(2.0))  # half as frequent
    torch.testing.assert_close(weights[11], torch.tensor(0.5))
    unseen = [c for c in range(FREE_LABEL + 1) if c not in (0, 4, 11)]
    assert torch.equal(weights[unseen], torch.ones(len(unseen)))  # 5 included: unsupervised
    # on real pseudo labels: rarer labels get larger weights
    real = median_frequency_weights(records)
    assert real.shape == (18,) and torch.isfinite(real).all() and (real > 0).all()
    counts = sum(torch.bincount(r.semantics[r.supervised].flatten(), minlength=18) for r in records)
    assert isinstance(counts, torch.Tensor)
    seen = (counts > 0).nonzero().flatten().tolist()
    for a in seen:
        for b in seen:
            if counts[a] < counts[b]:
                assert real[a] > real[b], (a, b)
    assert torch.isclose(real[seen], torch.tensor(1.0)).any()  # the median label(s)
    nothing = labelled(records[0], {}, unsupervised=7)
    assert torch.equal(median_frequency_weights([nothing]), torch.ones(18))


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
    assert all(math.isnan(perfect[name]) for name in PEOPLE_SCORES)  # no counts given
    scores = evaluate(GaussianPredictor(width=4), records[:1])
    assert set(scores) == {
        "IoU", "mIoU", "InsM", "ScnM", "HCM", "RayIoU", "vehicles", "articulated",
        "people voxels", "people blocks",
    }  # fmt: skip
    assert set(scores) == set(SCORES)


def with_people_blocks(record: SceneRecord) -> tuple[SceneRecord, list[int]]:
    """``record`` whose reference frame has people on three 8 x 8 blocks (16 x 48 images:
    2 x 6 blocks a camera), and those blocks' Gaussian indices (camera, row, column)."""
    semantics = record.semantics.clone()
    ref = record.reference
    semantics[ref] = 11  # driveable surface everywhere else
    blocks = [(0, 0, 0, 7), (2, 1, 5, 2), (5, 1, 0, 6)]  # camera, row, column, label
    for camera, row, col, label in blocks:
        semantics[ref, camera, row * 8 : row * 8 + 8, col * 8 : col * 8 + 8] = label
    semantics[ref, 3, 0:8, 8:11] = 7  # a minority of its block: not a people block
    indices = [camera * 12 + row * 6 + col for camera, row, col, _ in blocks]
    return dataclasses.replace(record, semantics=semantics), indices


def with_argmax(prediction: Prediction, labels: torch.Tensor) -> Prediction:
    logits = torch.full_like(prediction.logits, -5.0)
    logits[0, torch.arange(labels.shape[0]), labels] = 5.0
    return dataclasses.replace(prediction, logits=logits)


def test_people_counts(records: list[SceneRecord]) -> None:
    record, people = with_people_blocks(records[0])
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    prediction = predict(network, record)
    n = prediction.logits.shape[1]
    assert n == 72
    # the ground truth as the labels: as many people voxels as there are
    counts = people_counts(record.occupancy, prediction, record)
    assert counts.predicted_voxels == counts.true_voxels > 0
    assert counts.scores()["people voxels"] == pytest.approx(100.0)
    free = torch.full_like(record.occupancy, FREE_LABEL)
    assert people_counts(free, prediction, record).predicted_voxels == 0
    # every Gaussian a person / a cyclist: every people block right
    for label in HUMAN_CENTRIC_CLASSES:
        everyone = with_argmax(prediction, torch.full((n,), label))
        counts = people_counts(record.occupancy, everyone, record)
        assert counts.blocks == 3 and counts.blocks_right == 3
        assert counts.scores()["people blocks"] == pytest.approx(100.0)
    nobody = people_counts(record.occupancy, with_argmax(prediction, torch.full((n,), 4)), record)
    assert nobody.blocks == 3 and nobody.blocks_right == 0
    assert nobody.scores()["people blocks"] == 0.0
    # people on exactly the people blocks' Gaussians (camera, row, column order), and on
    # every other Gaussian but those
    labels = torch.full((n,), 4)
    labels[people] = 7
    exact = people_counts(record.occupancy, with_argmax(prediction, labels), record)
    assert exact.blocks_right == 3
    inverse = torch.where(labels == 7, 4, 7)
    assert (
        people_counts(record.occupancy, with_argmax(prediction, inverse), record).blocks_right == 0
    )
    # a prediction that does not tile the images in square blocks
    odd = dataclasses.replace(prediction, logits=prediction.logits[:, :70])
    with pytest.raises(ValueError, match="prediction"):
        people_counts(record.occupancy, odd, record)


def test_people_counts_add_and_score() -> None:
    a = PeopleCounts(predicted_voxels=3, true_voxels=4, blocks=2, blocks_right=1)
    b = PeopleCounts(predicted_voxels=5, true_voxels=4, blocks=0, blocks_right=0)
    assert a + b == PeopleCounts(8, 8, 2, 1)
    assert a + PeopleCounts() == a and sum([a, b], PeopleCounts()) == a + b
    assert (a + b).scores() == {"people voxels": 100.0, "people blocks": 50.0}
    assert set(PeopleCounts().scores()) == set(PEOPLE_SCORES)
    assert all(math.isnan(v) for v in PeopleCounts().scores().values())
    only_voxels = PeopleCounts(predicted_voxels=6, true_voxels=4).scores()
    assert only_voxels["people voxels"] == 150.0 and math.isnan(only_voxels["people blocks"])
    only_blocks = PeopleCounts(predicted_voxels=6, blocks=4, blocks_right=4).scores()
    assert math.isnan(only_blocks["people voxels"]) and only_blocks["people blocks"] == 100.0


def test_predict_scene_scores_people(records: list[SceneRecord]) -> None:
    record = records[0]
    network = GaussianPredictor(block=8, width=4, latent_dim=3)
    labels, counts = predict_scene(network, record)
    assert labels.shape == record.occupancy.shape
    assert counts == people_counts(labels, predict(network, record), record)
    assert counts.true_voxels > 0
    with pytest.raises(ValueError, match="people"):
        score_scenes([labels, labels], records, [counts])


def test_people_blocks_work_when_the_block_does_not_divide_the_image() -> None:
    config = DataConfig(train_scenes=1, heldout_scenes=1, image_size=(20, 44))
    records = load_scenes(scene_seeds(0, 0, 1), config, None)
    network = GaussianPredictor(block=8, width=4)
    scores = evaluate(network, records)
    assert predict(network, records[0]).gaussians.num_gaussians == 6 * 3 * 6  # ceil(20/8) x ...
    assert set(PEOPLE_SCORES) <= set(scores)
