"""The demo's pictures: BEV panels mark the scored region and carry the frame's score; the
camera picture names its camera and frame."""

from __future__ import annotations

import pytest
import torch

from dego import SyntheticScene
from dego.data.synthetic import CAMERAS
from dego.demo import DemoClip, FitConfig, fit_scene
from dego.metrics import OccupancyMetrics


@pytest.fixture(scope="module")
def clip() -> DemoClip:
    return DemoClip.from_scene(SyntheticScene(0, num_frames=2, image_size=(16, 44)))


def test_bev_figure_greys_the_unscored_columns_and_titles_the_frames_score(clip: DemoClip) -> None:
    pytest.importorskip("matplotlib")
    from dego.demo.pictures import bev_figure

    index = clip.num_frames - 1
    labels = clip.occupancy[index].clone()
    labels[: labels.shape[0] // 2] = 0  # a half-wrong prediction: a score well below 100
    metrics = OccupancyMetrics("weak")
    metrics.update(labels, clip.occupancy[index], clip.mask_camera[index])
    report = metrics.compute()
    figure = bev_figure(labels, clip, "static", index)
    prediction, truth = figure.axes[:2]
    title = prediction.get_title()
    offset = int(clip.times[index])
    assert title.startswith(f"static: prediction, t = {offset:+d}")
    assert f"IoU {100 * report.iou:.2f}, mIoU {100 * report.miou:.2f} (%, weak)" in title
    assert "outside the camera mask" in truth.get_title()
    assert [t.get_text() for t in figure.legends[0].get_texts()][-1] == "not scored"
    scored = clip.mask_camera[index].any(-1)
    if not bool(scored.all()):  # the synthetic cameras leave some columns unseen
        assert all(len(ax.collections) == 2 for ax in (prediction, truth))  # hatch, outline


def test_camera_figure_names_the_camera_and_the_frame(clip: DemoClip) -> None:
    pytest.importorskip("matplotlib")
    from dego.demo.pictures import camera_figure

    result = fit_scene(clip, "static", FitConfig(iterations=0, num_gaussians=200))
    title = camera_figure(result, clip, camera=3).get_suptitle()
    assert title.startswith(f"{CAMERAS[3][0]} (camera 3), frame t = +0")
    assert f"{clip.reference + 1} of {clip.num_frames}" in title
    for bad in (-1, len(CAMERAS)):
        with pytest.raises(ValueError, match="camera: expected an index"):
            camera_figure(result, clip, camera=bad)
    assert torch.equal(clip.times[clip.reference], torch.zeros_like(clip.times[0]))
