"""dego.viz.rerun with the real rerun-sdk, headless: record to a file, read it back with
rerun's own reader (its catalog / dataframe API) and check entities, times and values."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from jaxtyping import TypeCheckError

from dego import NUM_CLASSES, PALETTE, GaussianSet, VoxelGrid, normalize_quaternions
from tests.helpers.deformation import make_module
from tests.helpers.rrd import column, read_recording

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="reading recordings back needs rerun-sdk[catalog]")

from dego.viz import rerun as dr  # noqa: E402

SMALL = VoxelGrid(lower=(-1.0, -2.0, 0.0), upper=(1.0, 2.0, 1.0), voxel_size=0.5)  # 4 x 8 x 2


def small_labels(seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, NUM_CLASSES, SMALL.shape, generator=generator, dtype=torch.uint8)


def gaussians(n: int = 7, seed: int = 0, classes: int = NUM_CLASSES) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    return GaussianSet(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) + 0.1,
        opacities=torch.rand(n, generator=g) * 0.9 + 0.05,
        features=torch.randn(n, classes, generator=g),
    )


def record(path: Path, log) -> dict[str, list]:
    with dr.recording_file(path) as rec:
        log(rec)
    return read_recording(path)


@pytest.mark.parametrize("style", ["voxels", "boxes", "points"])
def test_occupancy_per_frame_voxels_and_classes(tmp_path: Path, style: str) -> None:
    grids = [small_labels(0), small_labels(1)]
    counts = []

    def log(rec) -> None:
        for frame, labels in enumerate(grids):
            counts.append(
                dr.log_occupancy(
                    "world/occ", labels, SMALL, style=style, frame=frame, recording=rec
                )
            )

    data = record(tmp_path / "occ.rrd", log)
    assert data["frame"] == [0, 1]
    for frame, labels in enumerate(grids):
        occupied = labels != 17
        assert counts[frame] == int(occupied.sum())
        ids = np.asarray(column(data, "world/occ", "class_id")[frame])
        expected = torch.bincount(labels[occupied].long(), minlength=NUM_CLASSES).numpy()
        np.testing.assert_array_equal(np.bincount(ids, minlength=NUM_CLASSES), expected)
        ijk = occupied.nonzero().numpy()
        np.testing.assert_array_equal(ids, labels[occupied].numpy())
        if style == "voxels":
            got = np.asarray(column(data, "world/occ", "VoxelGridMap:voxel_indices")[frame])
            np.testing.assert_array_equal(got, ijk)
            assert column(data, "world/occ", "VoxelGridMap:translation")[frame] == [[-1, -2, 0]]
            assert column(data, "world/occ", "VoxelGridMap:voxel_size")[frame] == [[0.5] * 3]
            colors = np.asarray(column(data, "world/occ", "VoxelGridMap:colors")[frame], np.uint32)
            rgb = np.stack([(colors >> 24) & 255, (colors >> 16) & 255, (colors >> 8) & 255], -1)
            np.testing.assert_array_equal(rgb, np.asarray(PALETTE)[labels[occupied].numpy()])
        else:
            archetype = "Boxes3D:centers" if style == "boxes" else "Points3D:positions"
            got = np.asarray(column(data, "world/occ", archetype)[frame])
            centers = SMALL.centers()[occupied].numpy()
            np.testing.assert_allclose(got, centers, atol=1e-6)


def test_full_occ3d_grid_is_one_entity_per_frame(tmp_path: Path) -> None:
    grid = VoxelGrid.occ3d()
    labels = torch.full(grid.shape, 17, dtype=torch.uint8)
    labels[:, :, 0] = 11  # a driveable floor: 40,000 voxels
    labels[90:110, 90:110, 1:5] = 4
    mask = torch.zeros(grid.shape, dtype=torch.bool)
    mask[:100] = True

    def log(rec) -> None:
        for frame in range(3):
            dr.log_occupancy("world/occ", labels, grid, mask=mask, frame=frame, recording=rec)

    data = record(tmp_path / "big.rrd", log)
    entities = {name.split(":")[0] for name in data if name.startswith("/world")}
    assert entities == {"/world/occ"}
    assert data["frame"] == [0, 1, 2]
    ids = np.asarray(column(data, "world/occ", "class_id")[2])
    assert (ids == 11).sum() == 100 * 200 and (ids == 4).sum() == 10 * 20 * 4


def test_gaussians_as_ellipsoids(tmp_path: Path) -> None:
    gs = gaussians()
    gs = gs.replace(opacities=gs.opacities.clone().index_fill_(0, torch.tensor([2]), 0.0))

    def log(rec) -> None:
        dr.log_gaussians("world/gaussians", gs, sigma=2.0, frame=4, recording=rec)

    data = record(tmp_path / "g.rrd", log)
    keep = gs.opacities > 0  # the zero-opacity Gaussian (padding) is left out
    assert data["frame"] == [4]
    centers = np.asarray(column(data, "world/gaussians", "Ellipsoids3D:centers")[0])
    np.testing.assert_allclose(centers, gs.means[keep].numpy(), rtol=1e-6)
    half = np.asarray(column(data, "world/gaussians", "Ellipsoids3D:half_sizes")[0])
    np.testing.assert_allclose(half, 2.0 * gs.scales[keep].numpy(), rtol=1e-6)
    quats = np.asarray(column(data, "world/gaussians", "Ellipsoids3D:quaternions")[0])
    wxyz = normalize_quaternions(gs.quats[keep]).numpy()
    np.testing.assert_allclose(quats, wxyz[:, [1, 2, 3, 0]], atol=1e-6)
    ids = column(data, "world/gaussians", "Ellipsoids3D:class_ids")[0]
    assert ids == gs.features[keep].argmax(-1).tolist()
    colors = np.asarray(column(data, "world/gaussians", "Ellipsoids3D:colors")[0], np.uint32)
    alpha = colors & 255
    np.testing.assert_array_equal(alpha, np.round(gs.opacities[keep].numpy() * 255))
    red = colors >> 24
    np.testing.assert_array_equal(red, np.asarray(PALETTE)[ids][:, 0])


def test_gaussians_without_class_features_are_grey_and_splats_keep_scales(tmp_path: Path) -> None:
    gs = gaussians(classes=5)
    batched = gs.reshape_batch(1, 1)

    def log(rec) -> None:
        dr.log_gaussians("world/ellipsoids", batched, recording=rec, frame=0)
        dr.log_gaussians("world/splats", gs, style="splats", recording=rec, frame=0)

    data = record(tmp_path / "s.rrd", log)
    colors = np.asarray(column(data, "world/ellipsoids", "Ellipsoids3D:colors")[0], np.uint32)
    assert set((colors >> 8).tolist()) == {(160 << 16) | (160 << 8) | 160}
    scales = np.asarray(column(data, "world/splats", "GaussianSplats3D:scales")[0])
    np.testing.assert_allclose(scales, gs.scales.numpy(), rtol=1e-6)


def test_cameras_pose_pinhole_and_images(tmp_path: Path) -> None:
    angle = 0.3
    rotation = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]]
    )
    world_to_cam = torch.eye(4).repeat(2, 1, 1)
    world_to_cam[0, :3, :3] = rotation
    world_to_cam[:, :3, 3] = torch.tensor([[1.0, 2.0, 3.0], [0.0, -1.0, 0.5]])
    k = torch.tensor([[50.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]).repeat(2, 1, 1)
    images = torch.rand(2, 3, 24, 32)
    semantics = torch.randn(2, NUM_CLASSES, 24, 32)

    def log(rec) -> None:
        paths = dr.log_cameras(
            "world/cameras",
            world_to_cam,
            k,
            (24, 32),
            names=["front", "back"],
            images=images,
            depth=torch.rand(2, 24, 32),
            semantics=semantics,
            frame=0,
            recording=rec,
        )
        assert paths == ["world/cameras/front", "world/cameras/back"]

    data = record(tmp_path / "cams.rrd", log)
    for v, name in enumerate(["front", "back"]):
        entity = f"world/cameras/{name}"
        cam_to_world = torch.linalg.inv(world_to_cam[v].double())
        translation = column(data, entity, "Transform3D:translation")[0][0]
        np.testing.assert_allclose(translation, cam_to_world[:3, 3].numpy(), atol=1e-5)
        matrix = np.asarray(column(data, entity, "Transform3D:mat3x3")[0][0]).reshape(3, 3)
        np.testing.assert_allclose(
            matrix.T, cam_to_world[:3, :3].numpy(), atol=1e-6
        )  # column-major
        pinhole = np.asarray(column(data, entity, "Pinhole:image_from_camera")[0][0]).reshape(3, 3)
        np.testing.assert_allclose(pinhole.T, k[v].numpy())
        assert column(data, entity, "Pinhole:resolution")[0] == [[32, 24]]
        for child in ("image", "depth", "semantics"):
            assert any(key.startswith(f"/{entity}/{child}:") for key in data)


def test_deformation_frames_and_mask_colours(tmp_path: Path) -> None:
    module = make_module(feature_dim=NUM_CLASSES, dtype=torch.float32)
    canonical = gaussians(n=5).reshape_batch(1)
    output = module(canonical, canonical.features, torch.tensor([-1.0, 0.0, 1.0]))

    def log(rec) -> None:
        dr.log_deformation("world/deformed", output, [10, 11, 12], recording=rec)

    data = record(tmp_path / "d.rrd", log)
    assert data["frame"] == [10, 11, 12]
    for t in range(3):
        centers = np.asarray(column(data, "world/deformed/classes", "Ellipsoids3D:centers")[t])
        np.testing.assert_allclose(
            centers, output.gaussians.means[0, t].detach().numpy(), rtol=1e-6
        )
        colors = np.asarray(
            column(data, "world/deformed/rigidity", "Ellipsoids3D:colors")[t], np.uint32
        )
        m = output.rigid_mask[0].detach().numpy()
        m = m[t] if m.ndim == 2 else m
        expected = np.round((1 - m) * dr.RIGID_RGB[0] + m * dr.NONRIGID_RGB[0])
        np.testing.assert_array_equal(colors >> 24, expected)


def test_classes_are_the_annotation_context(tmp_path: Path) -> None:
    path = tmp_path / "c.rrd"
    with dr.recording_file(path) as rec:
        dr.log_bev("bev/gt", small_labels(), frame=0, recording=rec)
    static = read_recording(path, index=None)
    assert any(name.startswith("/:AnnotationContext") for name in static)


def test_bev_image_orientation(tmp_path: Path) -> None:
    labels = torch.full(SMALL.shape, 17, dtype=torch.uint8)
    labels[-1, -1, 0] = 4  # largest x (forward), largest y (left): the top-left pixel
    mask = torch.ones(SMALL.shape, dtype=torch.bool)
    mask[0] = False  # the nearest row is unscored: the bottom row of the picture
    path = tmp_path / "bev.rrd"
    with dr.recording_file(path) as rec:
        dr.log_bev("bev/gt", labels, mask=mask, frame=0, recording=rec)
    buffer = column(read_recording(path), "bev/gt", "Image:buffer")[0][0]
    image = np.asarray(buffer, np.uint8).reshape(SMALL.shape[0], SMALL.shape[1], 3)
    assert tuple(image[0, 0]) == PALETTE[4]
    stripes = {tuple(map(int, pixel)) for pixel in image[-1]}
    assert stripes == set(dr.UNSCORED_BEV_STRIPES)
    assert (image[1, 1] == 255).all()  # free: white


def test_recording_file_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "a.rrd"
    path.write_bytes(b"previous")
    with pytest.raises(RuntimeError, match="boom"), dr.recording_file(path) as rec:
        dr.log_occupancy("world/occ", small_labels(), SMALL, recording=rec)
        raise RuntimeError("boom")
    assert path.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.rrd"]


def test_recording_file_unwritable_is_refused_before_recording(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OSError, match="file"), dr.recording_file(blocker / "sub" / "a.rrd"):
        pytest.fail("the block must not run")
    with pytest.raises(IsADirectoryError), dr.recording_file(tmp_path):
        pytest.fail("the block must not run")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_recording_file_on_a_full_disk_is_one_oserror_naming_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The temporary file is a link to /dev/full, where every write fails with ENOSPC:
    rerun's own error (a RuntimeError) becomes one OSError naming the recording."""
    path = tmp_path / "a.rrd"
    path.write_bytes(b"previous")
    tmp = tmp_path / ".a.rrd.full.tmp"
    tmp.symlink_to("/dev/full")
    monkeypatch.setattr(dr, "temporary_name", lambda target: tmp)
    with pytest.raises(OSError) as caught, dr.recording_file(path):
        pytest.fail("the block must not run")
    message = str(caught.value)
    assert message.startswith(f"cannot write the recording {path}: ")
    assert "No space left on device" in message and "\n" not in message
    assert path.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.rrd"]


_FAULTY_DISK = """
import os, resource, signal, sys
from pathlib import Path
import torch
from dego import VoxelGrid
from dego.viz import rerun as dr

mode, folder = sys.argv[1], Path(sys.argv[2])
target, tmp = folder / "rec.rrd", folder / ".rec.rrd.faulty.tmp"
dr.temporary_name = lambda path: tmp
dr.FLUSH_TIMEOUT_S, dr._CLOSE_GRACE_S = 1.0, 1.0
if mode == "stalled":  # a file that takes nothing more once its 64 kB buffer is full
    os.mkfifo(tmp)
    reader = os.open(tmp, os.O_RDONLY | os.O_NONBLOCK)  # open, never read
else:  # a disk that fills up: every write past 64 kB fails
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64_000, resource.RLIM_INFINITY))
grid = VoxelGrid(lower=(0.0, 0.0, 0.0), upper=(64.0, 64.0, 8.0), voxel_size=1.0)
labels = torch.randint(0, 17, grid.shape, generator=torch.Generator().manual_seed(0))
try:
    with dr.recording_file(target) as rec:
        for frame in range(4):
            dr.log_occupancy("world/occ", labels, grid, frame=frame, recording=rec)
except OSError as error:
    print(f"OSError: {error}")
"""


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs POSIX fifos and rlimits")
@pytest.mark.parametrize("mode", ["full", "stalled"])
def test_recording_file_on_a_failing_disk_ends_with_one_oserror_and_no_temporary(
    tmp_path: Path, mode: str
) -> None:
    """A disk that fills up while recording, and one that stops taking data (rerun's
    flush used to wait forever, then its exit handler did): the block ends within
    FLUSH_TIMEOUT_S with one OSError naming the file, the temporary file is removed, and
    the process still exits. (A disk that fills up while rerun flushes can leave rerun's
    writer as stuck as a stalled one: either reason is right for "full".)"""
    start = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-c", _FAULTY_DISK, mode, str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert time.monotonic() - start < 45
    lines = result.stdout.splitlines()
    assert len(lines) == 1, result.stdout
    assert lines[0].startswith(f"OSError: cannot write the recording {tmp_path / 'rec.rrd'}: ")
    assert "did not take it within 1 s" in lines[0] or "is the disk full?" in lines[0]
    if mode == "stalled":
        assert "did not take it within 1 s" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_bad_input_is_refused_like_the_rest_of_dego(tmp_path: Path) -> None:
    with dr.recording_file(tmp_path / "bad.rrd") as rec:
        bad = small_labels().long()
        bad[0, 0, 0] = 18
        with pytest.raises(ValueError, match=r"labels: expected Occ3D labels in \[0, 17\]"):
            dr.log_occupancy("world/occ", bad, SMALL, recording=rec)
        with pytest.raises(ValueError, match=r"labels: shape \(4, 8, 2\) does not match"):
            dr.log_occupancy("world/occ", small_labels(), VoxelGrid.occ3d(), recording=rec)
        wrong = torch.ones(4, 8, 3, dtype=torch.bool)
        with pytest.raises(TypeCheckError, match="mask"):
            dr.log_occupancy("world/occ", small_labels(), SMALL, mask=wrong, recording=rec)
        with pytest.raises(TypeCheckError, match="mask"):
            dr.log_bev("bev/occ", small_labels(), mask=wrong, recording=rec)
        with pytest.raises(TypeCheckError, match="labels"):
            dr.log_occupancy("world/occ", small_labels().float(), SMALL, recording=rec)
        nan = gaussians()
        nan = nan.replace(means=nan.means.clone().index_fill_(0, torch.tensor([1]), math.nan))
        with pytest.raises(ValueError) as caught:
            dr.log_gaussians("world/g", nan, recording=rec)
        with pytest.raises(ValueError) as expected:
            nan.check_values()
        assert str(caught.value) == str(expected.value)
        with pytest.raises(ValueError, match="gaussians: expected one set"):
            dr.log_gaussians(
                "world/g",
                gaussians().reshape_batch(1).map(lambda n, x: x.expand(2, *x.shape[1:])),
                recording=rec,
            )
        with pytest.raises(ValueError, match="sigma"):
            dr.log_gaussians("world/g", gaussians(), sigma=0.0, recording=rec)
        with pytest.raises(TypeCheckError, match="intrinsics"):
            dr.log_cameras("world/c", torch.eye(4)[None], torch.eye(4)[None], (4, 4), recording=rec)
        with pytest.raises(ValueError, match="entity"):
            dr.log_occupancy("", small_labels(), SMALL, recording=rec)
        with pytest.raises(TypeError, match="recording"):
            dr.log_occupancy("world/occ", small_labels(), SMALL, recording="file.rrd")  # type: ignore[arg-type]


def test_without_recording_argument_logs_into_reruns_global_recording(tmp_path: Path) -> None:
    path = tmp_path / "global.rrd"
    rr.init("dego-global-test")
    rr.save(str(path))
    try:
        dr.log_classes()
        dr.log_occupancy("world/occ", small_labels(), SMALL, frame=3)
        dr.log_gaussians("world/gaussians", gaussians(), frame=3)
    finally:
        rr.disconnect()
    data = read_recording(path)
    assert data["frame"] == [3]
    assert len(column(data, "world/gaussians", "Ellipsoids3D:centers")[0]) == 7
    assert column(data, "world/occ", "class_id")[0] is not None


def test_a_rerun_without_the_unstable_archetypes_falls_back_or_refuses(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The version gate (rerun-sdk before VoxelGridMap / GaussianSplats3D, e.g. 0.24)."""
    monkeypatch.delattr(rr, "VoxelGridMap")
    monkeypatch.delattr(rr, "GaussianSplats3D")
    path = tmp_path / "old.rrd"
    with dr.recording_file(path) as rec:
        dr.log_occupancy("world/occ", small_labels(), SMALL, frame=0, recording=rec)  # boxes
        with pytest.raises(
            RuntimeError, match=r"style: 'voxels' needs rerun's VoxelGridMap.*'boxes'"
        ):
            dr.log_occupancy("world/occ", small_labels(), SMALL, style="voxels", recording=rec)
        with pytest.raises(RuntimeError, match=r"style: 'splats' needs .*'ellipsoids'"):
            dr.log_gaussians("world/g", gaussians(), style="splats", recording=rec)
    assert any(name.startswith("/world/occ:Boxes3D") for name in read_recording(path))
