"""Camera helpers: resize/crop intrinsics, lidar2img splitting, BEVDet augmentation folding."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from dego import quaternions_to_rotation_matrices
from dego.cameras import apply_image_aug, resize_crop_intrinsics, split_projection
from tests.helpers.strategies import batch_shapes, random_quaternions

NUSCENES_K = [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]]


def random_intrinsics(
    shape: tuple[int, ...], g: torch.Generator, dtype: torch.dtype, skew: bool = False
) -> torch.Tensor:
    """Pinhole ``K`` ``(*shape, 3, 3)``: log-uniform fx, fy in [50, 5000], cx, cy in [-500, 2000]."""
    f = torch.exp(torch.rand((*shape, 2), generator=g, dtype=dtype) * math.log(100) + math.log(50))
    c = torch.rand((*shape, 2), generator=g, dtype=dtype) * 2500 - 500
    k = torch.zeros(*shape, 3, 3, dtype=dtype)
    k[..., 0, 0], k[..., 1, 1] = f.unbind(-1)
    k[..., :2, 2] = c
    k[..., 2, 2] = 1
    if skew:
        k[..., 0, 1] = (torch.rand(shape, generator=g, dtype=dtype) * 2 - 1) * 0.1 * f[..., 0]
    return k


def random_camera(
    shape: tuple[int, ...], seed: int, dtype: torch.dtype = torch.float64, skew: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(K, R, t, lam)``: random intrinsics, a proper rotation, a translation and a scale."""
    g = torch.Generator().manual_seed(seed)
    k = random_intrinsics(shape, g, dtype, skew)
    rot = quaternions_to_rotation_matrices(random_quaternions(shape, g, dtype))
    t = torch.randn((*shape, 3), generator=g, dtype=dtype) * 20
    magnitude = torch.exp((torch.rand(shape, generator=g, dtype=dtype) * 2 - 1) * math.log(1e3))
    sign = torch.where(torch.rand(shape, generator=g, dtype=dtype) < 0.5, -1.0, 1.0).to(dtype)
    return k, rot, t, magnitude * sign


def compose(k: torch.Tensor, rot: torch.Tensor, t: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """``lam K [R | t]`` ``(*, 3, 4)``."""
    return lam[..., None, None] * (k @ torch.cat([rot, t.unsqueeze(-1)], dim=-1))


def as_4x4(p: torch.Tensor) -> torch.Tensor:
    bottom = torch.zeros_like(p[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([p, bottom], dim=-2)


# ---------------------------------------------------------------------------------------
# resize_crop_intrinsics
# ---------------------------------------------------------------------------------------


def test_nuscenes_resize_and_top_crop(dtype: torch.dtype, device: torch.device) -> None:
    k = torch.tensor(NUSCENES_K, dtype=dtype, device=device)
    out = resize_crop_intrinsics(k, 0.44, (140, 0))
    expected = torch.tensor(
        [[0.44 * 1266.4, 0.0, 0.44 * 816.3], [0.0, 0.44 * 1266.4, 0.44 * 491.5 - 140], [0, 0, 1]],
        dtype=dtype,
        device=device,
    )
    torch.testing.assert_close(out, expected)
    assert out.dtype == dtype and out.device.type == device.type
    # 900x1600 -> 396x704 -> 256x704: the image edges map onto the new edges.
    height, width = 900 * 0.44 - 140, 1600 * 0.44
    assert (round(height, 9), round(width, 9)) == (256, 704)


def test_per_axis_scale_and_left_crop() -> None:
    k = torch.tensor([[100.0, 2.0, 50.0], [0.0, 80.0, 40.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    out = resize_crop_intrinsics(k, (0.5, 0.25), crop=(3, 7))
    expected = torch.tensor(
        [[50.0, 1.0, 25.0 - 7], [0.0, 20.0, 10.0 - 3], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    torch.testing.assert_close(resize_crop_intrinsics(k, 1, (0, 0)), k, rtol=0, atol=0)


@given(batch_shapes, st.integers(0, 2**31 - 1))
def test_resize_crop_is_batched(shape: tuple[int, ...], seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    k = random_intrinsics(shape, g, torch.float64, skew=True)
    out = resize_crop_intrinsics(k, (0.3, 0.7), (11.5, -4))
    assert out.shape == (*shape, 3, 3)
    for index in itertools.product(*(range(n) for n in shape)):
        single = resize_crop_intrinsics(k[index], (0.3, 0.7), (11.5, -4))
        torch.testing.assert_close(out[index], single, rtol=0, atol=0)


@given(
    st.integers(0, 2**31 - 1),
    st.floats(0.05, 4.0),
    st.floats(0.05, 4.0),
    st.floats(-300, 300),
    st.floats(-300, 300),
)
def test_projected_point_lands_on_the_resized_cropped_pixel(
    seed: int, sx: float, sy: float, top: float, left: float
) -> None:
    g = torch.Generator().manual_seed(seed)
    k = random_intrinsics((8,), g, torch.float64, skew=True)
    points = torch.randn(8, 3, generator=g, dtype=torch.float64) * 10
    points[:, 2] = points[:, 2].abs() + 0.5  # in front of the camera
    pixels = (k @ points.unsqueeze(-1)).squeeze(-1)
    pixels = pixels[:, :2] / pixels[:, 2:]
    moved = (resize_crop_intrinsics(k, (sx, sy), (top, left)) @ points.unsqueeze(-1)).squeeze(-1)
    moved = moved[:, :2] / moved[:, 2:]
    scale = torch.tensor([sx, sy], dtype=torch.float64)
    offset = torch.tensor([left, top], dtype=torch.float64)
    torch.testing.assert_close(moved, pixels * scale - offset, rtol=1e-12, atol=1e-9)


def test_resize_crop_gradcheck() -> None:
    g = torch.Generator().manual_seed(0)
    k = random_intrinsics((2,), g, torch.float64, skew=True).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: resize_crop_intrinsics(x, (0.4, 0.6), (9, 3)), (k,))


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"scale": 0.0}, "scale"),
        ({"scale": -0.5}, "scale"),
        ({"scale": math.nan}, "scale"),
        ({"scale": math.inf}, "scale"),
        ({"scale": (0.5, 0.0)}, "scale"),
        ({"scale": True}, "scale"),
        ({"scale": 0.5, "crop": (math.nan, 0)}, "crop"),
        ({"scale": 0.5, "crop": (0, -math.inf)}, "crop"),
    ],
)
def test_resize_crop_rejects_bad_numbers(kwargs: dict, name: str) -> None:
    k = torch.tensor(NUSCENES_K)
    with pytest.raises(ValueError, match=f"^{name}: "):
        resize_crop_intrinsics(k, **kwargs)


# ---------------------------------------------------------------------------------------
# split_projection
# ---------------------------------------------------------------------------------------


@given(
    batch_shapes,
    st.integers(0, 2**31 - 1),
    st.booleans(),
    st.booleans(),
)
def test_split_projection_recovers_the_camera(
    shape: tuple[int, ...], seed: int, skew: bool, square: bool
) -> None:
    k, rot, t, lam = random_camera(shape, seed, skew=skew)
    p = compose(k, rot, t, lam)
    world_to_cam, k_out = split_projection(as_4x4(p) if square else p)
    assert world_to_cam.shape == (*shape, 4, 4) and k_out.shape == (*shape, 3, 3)
    torch.testing.assert_close(k_out, k, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(world_to_cam[..., :3, :3], rot, rtol=0, atol=1e-6)
    torch.testing.assert_close(world_to_cam[..., :3, 3], t, rtol=1e-6, atol=1e-6)
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(*shape, 4)
    torch.testing.assert_close(world_to_cam[..., 3, :], last, rtol=0, atol=0)
    # round trip: K @ world_to_cam[:3] is P / lambda (lambda > 0 or < 0) to 1e-6 relative
    normalised = p / lam[..., None, None]
    error = (k_out @ world_to_cam[..., :3, :] - normalised).abs().amax(dim=(-1, -2))
    assert bool((error <= 1e-6 * normalised.abs().amax(dim=(-1, -2))).all())
    # K: upper triangular, positive focal lengths, K[2, 2] = 1; R: proper rotation
    assert bool((k_out[..., 1, 0] == 0).all() & (k_out[..., 2, :2] == 0).all())
    assert bool((k_out[..., 0, 0] > 0).all() & (k_out[..., 1, 1] > 0).all())
    torch.testing.assert_close(k_out[..., 2, 2], torch.ones(shape, dtype=torch.float64))
    r = world_to_cam[..., :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(r)
    torch.testing.assert_close(r @ r.mT, eye, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(shape, dtype=torch.float64))
    if not skew:
        assert bool((k_out[..., 0, 1].abs() <= 1e-9 * k[..., 0, 0]).all())


def test_split_projection_float32_and_device(dtype: torch.dtype, device: torch.device) -> None:
    k, rot, t, lam = random_camera((64,), seed=1, skew=True)
    p = compose(k, rot, t, lam)
    world_to_cam, k_out = split_projection(p.to(dtype=dtype, device=device))
    assert world_to_cam.dtype == k_out.dtype == dtype
    assert world_to_cam.device.type == k_out.device.type == device.type
    world_to_cam, k_out = world_to_cam.cpu().double(), k_out.cpu().double()
    normalised = p / lam[..., None, None]
    rel = (k_out @ world_to_cam[..., :3, :] - normalised).abs().amax(dim=(-1, -2))
    rel = rel / normalised.abs().amax(dim=(-1, -2))
    tol = 1e-13 if dtype == torch.float64 else 5e-6
    assert float(rel.max()) <= tol, float(rel.max())
    # the parts themselves: float32 loses another digit or so on R and t
    rtol = 1e-10 if dtype == torch.float64 else 5e-5
    torch.testing.assert_close(k_out, k, rtol=rtol, atol=rtol * 100)
    torch.testing.assert_close(world_to_cam[:, :3, :3], rot, rtol=0, atol=rtol)
    torch.testing.assert_close(world_to_cam[:, :3, 3], t, rtol=rtol, atol=rtol * 20)


def test_split_projection_bevformer_style_4x4() -> None:
    # mmdet3d: lidar2img = viewpad @ lidar2cam_rt.T with K padded to 4x4
    k = torch.tensor(NUSCENES_K, dtype=torch.float64)
    rot = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    t = torch.tensor([0.1, 1.5, -0.8], dtype=torch.float64)
    viewpad = torch.eye(4, dtype=torch.float64)
    viewpad[:3, :3] = k
    lidar2cam = torch.eye(4, dtype=torch.float64)
    lidar2cam[:3, :3], lidar2cam[:3, 3] = rot, t
    world_to_cam, k_out = split_projection((viewpad @ lidar2cam).expand(2, 6, 4, 4))
    torch.testing.assert_close(k_out, k.expand(2, 6, 3, 3), rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(world_to_cam, lidar2cam.expand(2, 6, 4, 4), rtol=0, atol=1e-12)


def test_split_projection_empty_batch() -> None:
    world_to_cam, k = split_projection(torch.zeros(0, 3, 4))
    assert world_to_cam.shape == (0, 4, 4) and k.shape == (0, 3, 3)


def test_split_projection_gradcheck() -> None:
    k, rot, t, lam = random_camera((2,), seed=3, skew=True)
    k = k / k.abs().amax(dim=(-1, -2), keepdim=True)  # keep the entries O(1) for finite diffs
    k[..., 2, 2] = 1
    p = compose(k, rot, t, lam).requires_grad_(True)
    assert torch.autograd.gradcheck(split_projection, (p,))


def _nearly_singular() -> torch.Tensor:
    p = compose(*random_camera((), seed=5))
    p[1, :3] = p[0, :3] * 2 + 1e-12 * p[0, :3].abs().max()
    return p


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: torch.zeros(3, 4), "singular"),
        (lambda: torch.eye(4)[:3] * torch.tensor([[1.0], [1.0], [0.0]]), "singular"),
        (_nearly_singular, "singular"),
        (
            lambda: torch.eye(4)[:3] + torch.tensor([[0, 0, 0, math.nan]] + [[0.0] * 4] * 2),
            "finite",
        ),
        (lambda: torch.eye(4)[:3] * math.inf, "finite"),
        (lambda: torch.eye(4) * 2, r"\[0, 0, 0, 1\]"),
        (
            lambda: torch.eye(4) + torch.tensor([[0.0] * 4] * 3 + [[1e-3, 0, 0, 0]]),
            r"\[0, 0, 0, 1\]",
        ),
    ],
)
def test_split_projection_rejects_bad_projections(make, match: str) -> None:
    with pytest.raises(ValueError, match=f"^projection: .*{match}"):
        split_projection(make())


# ---------------------------------------------------------------------------------------
# apply_image_aug
# ---------------------------------------------------------------------------------------


@given(
    batch_shapes,
    st.integers(0, 2**31 - 1),
    st.floats(0.05, 4.0),
    st.floats(-300, 300),
    st.floats(-300, 300),
)
def test_scale_and_translation_equal_resize_crop(
    shape: tuple[int, ...], seed: int, s: float, top: float, left: float
) -> None:
    g = torch.Generator().manual_seed(seed)
    k = random_intrinsics(shape, g, torch.float64, skew=True)
    post_rot = torch.diag(torch.tensor([s, s], dtype=torch.float64)).expand(*shape, 2, 2)
    post_tran = torch.tensor([-left, -top], dtype=torch.float64).expand(*shape, 2)
    out = apply_image_aug(k, post_rot, post_tran)
    torch.testing.assert_close(out, resize_crop_intrinsics(k, s, (top, left)), rtol=0, atol=0)


def test_per_axis_scale_equals_resize_crop(dtype: torch.dtype, device: torch.device) -> None:
    k = torch.tensor(NUSCENES_K, dtype=dtype, device=device)
    post_rot = torch.tensor([[0.44, 0.0], [0.0, 0.5]], dtype=dtype, device=device)
    post_tran = torch.tensor([-8.0, -140.0], dtype=dtype, device=device)
    torch.testing.assert_close(
        apply_image_aug(k, post_rot, post_tran), resize_crop_intrinsics(k, (0.44, 0.5), (140, 8))
    )


@pytest.mark.slow
@given(batch_shapes, st.integers(0, 2**31 - 1))
def test_bevdet_3x3_layout_equals_2x2_layout_and_maps_pixels(
    shape: tuple[int, ...], seed: int
) -> None:
    g = torch.Generator().manual_seed(seed)
    k = random_intrinsics(shape, g, torch.float64, skew=True)
    scales = torch.rand((*shape, 2), generator=g, dtype=torch.float64) + 0.2
    post_rot = torch.diag_embed(scales)
    post_tran = torch.randn((*shape, 2), generator=g, dtype=torch.float64) * 100
    rot3 = torch.eye(3, dtype=torch.float64).repeat(*shape, 1, 1)
    rot3[..., :2, :2] = post_rot
    tran3 = torch.cat([post_tran, torch.zeros(*shape, 1, dtype=torch.float64)], dim=-1)
    out = apply_image_aug(k, post_rot, post_tran)
    assert out.shape == (*shape, 3, 3)
    for rot, tran in ((rot3, tran3), (rot3, post_tran), (post_rot, tran3)):
        torch.testing.assert_close(apply_image_aug(k, rot, tran), out, rtol=0, atol=0)
    # BEVDet: a projected pixel p becomes post_rot @ p + post_tran
    points = torch.randn((*shape, 3), generator=g, dtype=torch.float64)
    points[..., 2] = points[..., 2].abs() + 0.5
    pix = (k @ points.unsqueeze(-1)).squeeze(-1)
    pix = pix[..., :2] / pix[..., 2:]
    moved = (out @ points.unsqueeze(-1)).squeeze(-1)
    moved = moved[..., :2] / moved[..., 2:]
    expected = (post_rot @ pix.unsqueeze(-1)).squeeze(-1) + post_tran
    torch.testing.assert_close(moved, expected, rtol=1e-12, atol=1e-9)


def test_identity_augmentation_is_identity(dtype: torch.dtype, device: torch.device) -> None:
    k = torch.tensor(NUSCENES_K, dtype=dtype, device=device).expand(2, 3, 3)
    eye = torch.eye(3, dtype=dtype, device=device).expand(2, 3, 3)
    out = apply_image_aug(k, eye, torch.zeros(2, 3, dtype=dtype, device=device))
    torch.testing.assert_close(out, k, rtol=0, atol=0)


def test_apply_image_aug_gradcheck() -> None:
    g = torch.Generator().manual_seed(0)
    k = random_intrinsics((2,), g, torch.float64, skew=True).requires_grad_(True)
    scales = (torch.rand(2, 2, generator=g, dtype=torch.float64) + 0.5).requires_grad_(True)
    post_tran = torch.randn(2, 2, generator=g, dtype=torch.float64).requires_grad_(True)
    # post_rot is built from its diagonal: perturbing an off-diagonal would be a rotation
    assert torch.autograd.gradcheck(
        lambda k, s, t: apply_image_aug(k, torch.diag_embed(s), t), (k, scales, post_tran)
    )


def test_tiny_off_diagonal_rounding_is_dropped() -> None:
    k = torch.tensor(NUSCENES_K, dtype=torch.float64)
    angle = 1e-9  # cos/sin of an (almost) zero rotation angle
    post_rot = 0.5 * torch.tensor(
        [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]],
        dtype=torch.float64,
    )
    out = apply_image_aug(k, post_rot, torch.zeros(2, dtype=torch.float64))
    assert float(out[0, 1]) == 0 and float(out[1, 0]) == 0


@pytest.mark.parametrize("angle", [1e-3, math.pi / 2, math.pi])
def test_rotation_raises(angle: float) -> None:
    k = torch.tensor(NUSCENES_K)
    c, s = math.cos(angle), math.sin(angle)
    post_rot = torch.tensor([[c, -s], [s, c]])
    with pytest.raises(ValueError, match=r"^post_rot: .*warp") as info:
        apply_image_aug(k, post_rot, torch.zeros(2))
    assert "world_to_cam" in str(info.value)


@pytest.mark.parametrize("diagonal", [(-1.0, 1.0), (1.0, -1.0), (0.0, 1.0)])
def test_flip_raises(diagonal: tuple[float, float]) -> None:
    k = torch.tensor(NUSCENES_K).expand(3, 3, 3)
    post_rot = torch.eye(2).repeat(3, 1, 1)
    post_rot[1] = torch.diag(torch.tensor(diagonal))  # one bad camera in the batch
    with pytest.raises(ValueError, match=r"^post_rot: .*warp"):
        apply_image_aug(k, post_rot, torch.zeros(3, 2))


@pytest.mark.parametrize(
    ("post_rot", "post_tran", "name"),
    [
        (torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 2]]), torch.zeros(2), "post_rot"),
        (torch.tensor([[1.0, 0, 5], [0, 1, 0], [0, 0, 1]]), torch.zeros(2), "post_rot"),
        (torch.tensor([[1.0, 0, 0], [0, 1, 0], [0.5, 0, 1]]), torch.zeros(2), "post_rot"),
        (torch.eye(2), torch.tensor([0.0, 0.0, 1.0]), "post_tran"),
        (torch.eye(2) * math.nan, torch.zeros(2), "post_rot"),
        (torch.eye(2), torch.tensor([math.inf, 0.0]), "post_tran"),
    ],
)
def test_apply_image_aug_rejects_bad_layouts(
    post_rot: torch.Tensor, post_tran: torch.Tensor, name: str
) -> None:
    with pytest.raises(ValueError, match=f"^{name}: "):
        apply_image_aug(torch.tensor(NUSCENES_K), post_rot, post_tran)


# ---------------------------------------------------------------------------------------
# shapes and dtypes
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "call",
    [
        lambda: resize_crop_intrinsics(torch.zeros(3, 4), 0.5),
        lambda: resize_crop_intrinsics(torch.zeros(3, 3, dtype=torch.int64), 0.5),
        lambda: resize_crop_intrinsics(torch.eye(3), "0.5"),
        lambda: resize_crop_intrinsics(torch.eye(3), 0.5, (1, 2, 3)),
        lambda: split_projection(torch.zeros(4, 3)),
        lambda: split_projection(torch.zeros(3, 3)),
        lambda: apply_image_aug(torch.eye(3), torch.eye(2), torch.zeros(4)),
        lambda: apply_image_aug(torch.eye(3).expand(2, 3, 3), torch.eye(2), torch.zeros(2)),
        lambda: apply_image_aug(torch.eye(3), torch.eye(4), torch.zeros(2)),
    ],
)
def test_wrong_shapes_and_types_raise(call) -> None:
    with pytest.raises((TypeError, ValueError)):
        call()


# -- camera arguments of the renderers ----------------------------------------------------
@pytest.mark.parametrize("keyword", [False, True])
def test_missing_camera_axes_name_the_argument_and_its_shape(keyword: bool) -> None:
    """A camera argument without its (B, V) axes names itself, its expected shape and how
    to add the axes (issue 26: an ``intrinsics`` error advised ``world_to_cam[None]``)."""
    from dego import DifferentiableSplatter, splat
    from tests.helpers.strategies import make_gaussian_set

    gaussians = make_gaussian_set((1,), 4)
    world_to_cam = torch.eye(4, dtype=torch.float64).expand(1, 1, 4, 4)
    k = torch.tensor(NUSCENES_K, dtype=torch.float64).expand(1, 1, 3, 3)
    cases = [
        (
            world_to_cam,
            k[0],
            r"intrinsics: expected shape \(B, V, 3, 3\), got \(1, 3, 3\)",
            "intrinsics[None]",
        ),
        (
            world_to_cam,
            k[0, 0],
            r"intrinsics: expected shape \(B, V, 3, 3\), got \(3, 3\)",
            "intrinsics[None, None]",
        ),
        (
            world_to_cam[0],
            k,
            r"world_to_cam: expected shape \(B, V, 4, 4\), got \(1, 4, 4\)",
            "world_to_cam[None]",
        ),
        (
            world_to_cam[0, 0],
            k,
            r"world_to_cam: expected shape \(B, V, 4, 4\)",
            "world_to_cam[None, None]",
        ),
    ]
    module = DifferentiableSplatter()
    for w2c, intrinsics, match, advice in cases:
        for render in (splat, module):
            with pytest.raises(ValueError, match=match) as info:
                if keyword:
                    render(gaussians, world_to_cam=w2c, intrinsics=intrinsics, image_size=(8, 8))
                else:
                    render(gaussians, w2c, intrinsics, (8, 8))
            message = str(info.value)
            assert advice in message, message
            other = "world_to_cam" if advice.startswith("intrinsics") else "intrinsics"
            assert f"{other}[" not in message, message
