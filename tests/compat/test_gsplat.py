"""``dego.compat.gsplat.rasterization``: gsplat's call, layouts and return values on dego's splatter."""

from __future__ import annotations

import enum
import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from dego import GaussianSet, spherical_harmonics, splat
from dego.compat.gsplat import rasterization
from tests.helpers.splatting import make_cameras, make_scene_gaussians

SIZE = (20, 28)  # (H, W)
RENDER_MODES = ["RGB", "D", "ED", "RGB+D", "RGB+ED"]


def gsplat_inputs(
    batch: tuple[int, ...], cameras: int, n: int, channels: int, *, seed: int, per_camera: bool
) -> dict[str, Tensor]:
    """gsplat-layout tensors: ``means [..., N, 3]``, ``viewmats [..., C, 4, 4]`` and so on."""
    flat = math.prod(batch)
    gs = make_scene_gaussians(flat, n, SIZE, seed=seed, spread=1.2)
    w2c, k = make_cameras(flat, cameras, SIZE, seed=seed)
    g = torch.Generator().manual_seed(seed)
    colors_shape = (flat, cameras, n, channels) if per_camera else (flat, n, channels)
    return {
        "means": gs.means.reshape(*batch, n, 3),
        "quats": gs.quats.reshape(*batch, n, 4),
        "scales": gs.scales.reshape(*batch, n, 3),
        "opacities": gs.opacities.reshape(*batch, n),
        "colors": torch.rand(colors_shape, generator=g, dtype=torch.float64).reshape(
            *batch, *colors_shape[1:]
        ),
        "viewmats": w2c.reshape(*batch, cameras, 4, 4),
        "Ks": k.reshape(*batch, cameras, 3, 3),
        "backgrounds": torch.rand(flat, cameras, channels, generator=g, dtype=torch.float64)
        .reshape(*batch, cameras, channels),
    }  # fmt: skip


def splat_equivalent(
    t: dict[str, Tensor], render_mode: str, **options: Any
) -> tuple[Tensor, Tensor, Any]:
    """The same render through ``dego.splat`` by hand, put into gsplat's output layout."""
    batch = tuple(t["means"].shape[:-2])
    n, cameras = t["means"].shape[-2], t["viewmats"].shape[-3]
    flat = math.prod(batch)
    gs = GaussianSet(
        means=t["means"].reshape(flat, n, 3),
        quats=t["quats"].reshape(flat, n, 4),
        scales=t["scales"].reshape(flat, n, 3),
        opacities=t["opacities"].reshape(flat, n),
    )
    with_colors = render_mode.startswith("RGB")
    depth_mode = {"RGB": "none", "D": "accumulated", "ED": "expected"}[render_mode.split("+")[-1]]
    colors = t["colors"]
    colors = colors.reshape(flat, *colors.shape[len(batch) :])
    out = splat(
        gs,
        t["viewmats"].reshape(flat, cameras, 4, 4),
        t["Ks"].reshape(flat, cameras, 3, 3),
        SIZE,
        features=colors if with_colors else None,
        background=t["backgrounds"].reshape(flat, cameras, -1)
        if with_colors and "backgrounds" in t
        else None,
        depth_mode=depth_mode,
        **options,
    )
    channels = [out.features.permute(0, 1, 3, 4, 2)] if with_colors else []
    if out.depth is not None:
        channels.append(out.depth.unsqueeze(-1))
    image = torch.cat(channels, -1)
    return (
        image.reshape(*batch, cameras, *SIZE, image.shape[-1]),
        out.alpha.reshape(*batch, cameras, *SIZE, 1),
        out,
    )


def call(t: dict[str, Tensor], **kwargs: Any) -> tuple[Tensor, Tensor, dict]:
    height, width = SIZE
    return rasterization(
        t["means"], t["quats"], t["scales"], t["opacities"], t["colors"], t["viewmats"],
        t["Ks"], width, height, **kwargs,
    )  # fmt: skip


@pytest.mark.slow
@settings(max_examples=40)
@given(
    batch=st.sampled_from([(), (2,), (2, 1)]),
    cameras=st.integers(1, 2),
    render_mode=st.sampled_from(RENDER_MODES),
    per_camera=st.booleans(),
    backgrounds=st.booleans(),
    packed=st.booleans(),
    radius_clip=st.sampled_from([0.0, 3.0]),
    rasterize_mode=st.sampled_from(["classic", "antialiased"]),
    version=st.sampled_from(["1.2.0", "1.4", "1.5.3", "1.6"]),
    seed=st.integers(0, 1000),
)
def test_equals_dego_splat_in_every_mode_and_layout(
    batch: tuple[int, ...],
    cameras: int,
    render_mode: str,
    per_camera: bool,
    backgrounds: bool,
    packed: bool,
    radius_clip: float,
    rasterize_mode: str,
    version: str,
    seed: int,
) -> None:
    t = gsplat_inputs(batch, cameras, 15, 3, seed=seed, per_camera=per_camera)
    if not backgrounds:
        t.pop("backgrounds")
    options = {"radius_clip": radius_clip, "rasterize_mode": rasterize_mode}
    colors, alphas, meta = call(
        t,
        render_mode=render_mode,
        packed=packed,
        gsplat_version=version,
        backgrounds=t.get("backgrounds"),
        **options,
    )
    rule = "gsplat>=1.5" if version >= "1.5" else "gsplat<=1.4"
    max_alpha = 0.99 if version >= "1.6" else 0.999
    expected_colors, expected_alphas, out = splat_equivalent(
        t, render_mode, radius_rule=rule, max_alpha=max_alpha, **options
    )
    channels = {"RGB": 3, "D": 1, "ED": 1, "RGB+D": 4, "RGB+ED": 4}[render_mode]
    assert colors.shape == (*batch, cameras, *SIZE, channels)  # gsplat's documented shapes
    assert alphas.shape == (*batch, cameras, *SIZE, 1)
    assert torch.equal(colors, expected_colors)
    assert torch.equal(alphas, expected_alphas)

    n = 15
    dense_radii = out.projection.radii_xy if rule == "gsplat>=1.5" else out.radii
    dense_radii = dense_radii.reshape(*batch, cameras, n, *dense_radii.shape[3:])
    dense_means2d = out.projection.means2d.reshape(*batch, cameras, n, 2)
    if packed:
        b, c, g = meta["batch_ids"], meta["camera_ids"], meta["gaussian_ids"]
        flat_radii = dense_radii.reshape(-1, cameras, n, *dense_radii.shape[len(batch) + 2 :])
        assert torch.equal(meta["radii"], flat_radii[b, c, g])
        assert bool((flat_radii[b, c, g] > 0).all())
        assert int(b.numel()) == int(out.projection.visible.sum())
        assert torch.equal(meta["means2d"], dense_means2d.reshape(-1, cameras, n, 2)[b, c, g])
    else:
        assert meta["gaussian_ids"] is None and meta["camera_ids"] is None
        assert torch.equal(meta["radii"], dense_radii)
        assert torch.equal(meta["means2d"], dense_means2d)
        assert meta["depths"].shape == (*batch, cameras, n)
        assert meta["conics"].shape == (*batch, cameras, n, 3)
    assert (meta["width"], meta["height"], meta["tile_size"]) == (SIZE[1], SIZE[0], 16)
    assert (meta["tile_width"], meta["tile_height"]) == (2, 2)
    assert meta["n_cameras"] == cameras


@pytest.mark.parametrize("packed", [True, False])
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+D", "RGB+ED", "ED"])
def test_gradients_equal_dego_splat(packed: bool, render_mode: str) -> None:
    t = gsplat_inputs((2,), 2, 12, 3, seed=3, per_camera=False)
    leaves = {k: v.clone().requires_grad_(True) for k, v in t.items()}
    colors, alphas, _ = call(
        leaves, render_mode=render_mode, packed=packed, backgrounds=leaves["backgrounds"]
    )
    (colors.square().sum() + alphas.sum()).backward()
    reference = {k: v.clone().requires_grad_(True) for k, v in t.items()}
    # the adapter's default (gsplat_version=None) is splat's default
    expected_colors, expected_alphas, _ = splat_equivalent(reference, render_mode)
    (expected_colors.square().sum() + expected_alphas.sum()).backward()
    for name in ("means", "quats", "scales", "opacities", "colors", "backgrounds"):
        got, want = leaves[name].grad, reference[name].grad
        if want is None:
            assert got is None or float(got.abs().max()) == 0, name
        else:
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12, msg=name)


@pytest.mark.parametrize("packed", [True, False])
def test_means2d_grad_and_absgrad_for_densification(packed: bool) -> None:
    """3DGS densification reads ``meta["means2d"].grad`` (and ``.absgrad``) after backward."""
    t = gsplat_inputs((), 2, 12, 3, seed=4, per_camera=False)
    del t["backgrounds"]
    t["means"].requires_grad_(True)
    colors, _, meta = call(t, packed=packed, absgrad=True)
    meta["means2d"].retain_grad()  # what gsplat's strategies do
    (colors * torch.linspace(-1, 1, 3, dtype=torch.float64)).sum().backward()
    grad, absgrad = meta["means2d"].grad, meta["means2d"].absgrad
    assert grad is not None and grad.shape == meta["means2d"].shape == absgrad.shape
    assert bool((absgrad >= grad.abs() - 1e-12).all())
    assert float(absgrad.max()) > 0

    # the same numbers as dego.splat's own absgrad, in the other layout
    _, _, out = splat_equivalent(
        {k: v.detach().requires_grad_(k == "means") for k, v in t.items()},
        "RGB",
        absgrad=True,
    )
    out.projection.means2d.retain_grad()
    image = out.features.permute(0, 1, 3, 4, 2)
    (image * torch.linspace(-1, 1, 3, dtype=torch.float64)).sum().backward()
    dense = out.projection.means2d.absgrad[0]
    if packed:
        dense = dense[meta["camera_ids"], meta["gaussian_ids"]]
    torch.testing.assert_close(absgrad, dense, rtol=1e-12, atol=1e-12)


def test_gsplat_version_decides_the_radii_layout() -> None:
    t = gsplat_inputs((), 2, 10, 3, seed=0, per_camera=False)
    _, _, new = call(t, packed=False, gsplat_version="1.5")
    _, _, old = call(t, packed=False, gsplat_version="1.4.0")
    _, _, default = call(t, packed=False)  # splat's rule, gsplat <= 1.4
    assert new["radii"].shape == (2, 10, 2)
    assert old["radii"].shape == (2, 10)
    assert torch.equal(default["radii"], old["radii"])


def test_default_follows_dego_splat() -> None:
    """One default for both entry points: ``gsplat_version=None`` renders as ``splat``."""
    t = gsplat_inputs((), 2, 15, 3, seed=5, per_camera=False)
    colors, alphas, _ = call(t, backgrounds=t["backgrounds"])
    expected_colors, expected_alphas, _ = splat_equivalent(t, "RGB")
    assert torch.equal(colors, expected_colors)
    assert torch.equal(alphas, expected_alphas)
    assert torch.equal(colors, call(t, backgrounds=t["backgrounds"], gsplat_version="1.4")[0])


@pytest.mark.parametrize(
    ("version", "max_alpha"), [("1.0", 0.999), ("1.4", 0.999), ("1.5.3", 0.999), ("1.6.0", 0.99)]
)
def test_gsplat_version_decides_the_alpha_cap(version: str, max_alpha: float) -> None:
    """gsplat 1.6 caps alpha at 0.99 where 1.4 and 1.5 use 0.999 (its commit c5ff586b)."""
    t = gsplat_inputs((), 1, 1, 3, seed=0, per_camera=False)
    dtype = t["means"].dtype
    t["means"] = torch.tensor([[0.0, 0.0, 4.0]], dtype=dtype)  # in front of the camera
    t["scales"] = torch.full((1, 3), 10.0, dtype=dtype)  # wide: alpha > 0.999 at the centre
    t["opacities"] = torch.tensor([0.99999], dtype=dtype)
    t["viewmats"] = torch.eye(4, dtype=dtype)[None]
    _, alphas, _ = call(t, gsplat_version=version)
    assert float(alphas.max()) == pytest.approx(max_alpha, abs=1e-6)


def test_layout_only_and_default_valued_options_are_accepted() -> None:
    class RollingShutterType(enum.Enum):  # stands in for gsplat's enum
        GLOBAL = 0

    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    expected = call(t)[0]
    same = call(
        t,
        sparse_grad=True,
        channel_chunk=1,
        segmented=True,
        distributed=False,
        covars=None,
        with_ut=False,
        rolling_shutter=RollingShutterType.GLOBAL,
        camera_model="pinhole",
        sh_degree=None,
    )[0]
    assert torch.equal(same, expected)


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("camera_model", "fisheye"),
        ("camera_model", "ortho"),
        ("distributed", True),
        ("covars", torch.eye(3).expand(8, 3, 3)),
        ("with_ut", True),
        ("with_eval3d", True),
        ("radial_coeffs", torch.zeros(1, 6)),
        ("tangential_coeffs", torch.zeros(1, 2)),
        ("thin_prism_coeffs", torch.zeros(1, 4)),
        ("ftheta_coeffs", object()),
        ("rolling_shutter", "ROLLING_TOP_TO_BOTTOM"),
        ("viewmats_rs", torch.eye(4)[None]),
    ],
)
def test_unsupported_options_raise_not_implemented(option: str, value: Any) -> None:
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    with pytest.raises(NotImplementedError, match=rf"^{option}=") as caught:
        call(t, **{option: value})
    assert len(str(caught.value).splitlines()) == 1  # a tensor is described, not printed
    if isinstance(value, torch.Tensor):
        assert f"<tensor of shape {list(value.shape)}>" in str(caught.value)


def test_value_and_dtype_errors_name_gsplats_arguments() -> None:
    """Issue 41 (6): a gsplat caller wrote opacities=, colors=, viewmats=: the errors say so."""
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    logits = t["opacities"] * 8 - 4
    with pytest.raises(
        ValueError, match=r"^opacities: .*outside \[0, 1\].*torch\.sigmoid"
    ) as caught:
        call({**t, "opacities": logits})
    assert "gaussians." not in str(caught.value) and "from_tensors" not in str(caught.value)
    other = torch.float32 if t["means"].dtype == torch.float64 else torch.float64
    with pytest.raises(TypeError, match=rf"^colors: dtype {other} differs from means'"):
        call({**t, "colors": t["colors"].to(other)})
    bad = t["viewmats"].clone()
    bad[..., 3, 2] = 0.5
    with pytest.raises(ValueError, match=r"^viewmats: "):
        call({**t, "viewmats": bad})


def test_unknown_keyword_lists_the_accepted_names() -> None:
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    with pytest.raises(TypeError, match=r"unexpected keyword 'image_size'.*render_mode"):
        call(t, image_size=SIZE)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t: {"opacities": t["opacities"][..., None]}, r"opacities:.*squeeze"),
        (lambda t: {"quats": t["quats"][..., :3]}, r"quats: expected shape \[8, 4\]"),
        (lambda t: {"viewmats": t["viewmats"][None]}, r"viewmats: expected shape \[\.\.\., C"),
        (lambda t: {"Ks": t["Ks"][..., :2, :]}, r"Ks: expected shape \[1, 3, 3\]"),
        (lambda t: {"colors": t["colors"][:5]}, r"colors: expected shape \[8, D\]"),
        (lambda t: {"colors": t["colors"][:5, None]}, r"colors:.*\[8, K, 3\]"),
        (lambda t: {"means": t["means"].int()}, r"means: expected a floating-point tensor"),
    ],
)
def test_bad_shapes_name_the_argument(change: Any, message: str) -> None:
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    t |= change(t)
    with pytest.raises((ValueError, TypeError), match=message):
        call(t)


@pytest.mark.parametrize("version", ["2.0", "one", "", "1.-1", "0.9"])
def test_bad_gsplat_version_raises(version: str) -> None:
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    with pytest.raises(ValueError, match="gsplat_version"):
        call(t, gsplat_version=version)


def test_bad_render_mode_and_size_raise() -> None:
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    with pytest.raises(ValueError, match="render_mode"):
        call(t, render_mode="RGBD")
    with pytest.raises(TypeError, match="width, height"):
        rasterization(*(t[k] for k in ("means", "quats", "scales", "opacities", "colors")),
                      t["viewmats"], t["Ks"], 28.0, 20)  # fmt: skip


def test_runs_on_device(device: torch.device) -> None:
    t = {
        k: v.float().to(device)
        for k, v in gsplat_inputs((2,), 2, 10, 3, seed=2, per_camera=True).items()
    }
    colors, _, meta = call(t, render_mode="RGB+ED", backgrounds=t["backgrounds"])
    assert colors.device.type == device.type and meta["means2d"].device.type == device.type
    cpu = {k: v.cpu() for k, v in t.items()}
    expected = call(cpu, render_mode="RGB+ED", backgrounds=cpu["backgrounds"])[0]
    torch.testing.assert_close(colors.cpu(), expected, rtol=1e-4, atol=1e-4)


def sh_inputs(
    batch: tuple[int, ...], cameras: int, n: int, k: int, *, seed: int, per_camera: bool
) -> dict[str, Tensor]:
    """``gsplat_inputs`` with SH coefficients ``[..., (C,) N, K, 3]`` as ``colors``."""
    t = gsplat_inputs(batch, cameras, n, 3, seed=seed, per_camera=False)
    g = torch.Generator().manual_seed(seed + 1)
    lead = (*batch, cameras) if per_camera else batch
    t["colors"] = 0.5 * torch.randn(*lead, n, k, 3, generator=g, dtype=torch.float64)
    return t


def sh_colours_by_hand(t: dict[str, Tensor], degree: int) -> Tensor:
    """gsplat's recipe: camera centres from ``inverse(viewmats)``, SH + 0.5, clamped at 0."""
    centres = torch.linalg.inv(t["viewmats"])[..., :3, 3]  # [..., C, 3]
    directions = t["means"][..., None, :, :] - centres[..., :, None, :]  # [..., C, N, 3]
    coefficients = t["colors"]
    if coefficients.ndim == directions.ndim:  # [..., N, K, 3]: shared by the cameras
        coefficients = coefficients[..., None, :, :, :].expand(
            *directions.shape[:-1], *coefficients.shape[-2:]
        )
    return torch.clamp_min(spherical_harmonics(degree, directions, coefficients) + 0.5, 0.0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
@pytest.mark.parametrize(
    ("batch", "per_camera", "packed"),
    [((), False, True), ((2,), True, False), ((2, 1), False, False)],
)
def test_sh_colours_equal_evaluating_by_hand_then_rendering(
    degree: int, batch: tuple[int, ...], per_camera: bool, packed: bool
) -> None:
    t = sh_inputs(batch, 2, 15, 25, seed=degree, per_camera=per_camera)
    colors, alphas, meta = call(
        t, sh_degree=degree, packed=packed, backgrounds=t["backgrounds"], render_mode="RGB+ED"
    )
    raw = t | {"colors": sh_colours_by_hand(t, degree)}  # [..., C, N, 3] post-activation
    expected_colors, expected_alphas, expected_meta = call(
        raw, packed=packed, backgrounds=t["backgrounds"], render_mode="RGB+ED"
    )
    assert colors.shape == (*batch, 2, *SIZE, 4)
    torch.testing.assert_close(colors, expected_colors, rtol=1e-12, atol=1e-12)
    assert torch.equal(alphas, expected_alphas)
    assert torch.equal(meta["radii"], expected_meta["radii"])


def test_sh_extra_coefficients_are_ignored_and_gradients_flow() -> None:
    t = sh_inputs((), 2, 12, 16, seed=7, per_camera=False)
    low = t | {"colors": t["colors"][:, :4]}
    assert torch.equal(call(t, sh_degree=1)[0], call(low, sh_degree=1)[0])
    leaves = {k: v.clone().requires_grad_(k in ("colors", "means")) for k, v in t.items()}
    colors, _, _ = call(leaves, sh_degree=3)
    colors.square().sum().backward()
    for name in ("colors", "means"):
        grad = leaves[name].grad
        assert grad is not None and bool(grad.isfinite().all()) and float(grad.abs().max()) > 0


def test_sh_degree_zero_is_the_dc_term_plus_one_half() -> None:
    t = sh_inputs((), 1, 10, 1, seed=8, per_camera=False)
    dc = torch.clamp_min(0.5 / math.sqrt(math.pi) * t["colors"][:, 0] + 0.5, 0.0)  # [N, 3]
    expected = call(t | {"colors": dc})[0]
    torch.testing.assert_close(call(t, sh_degree=0)[0], expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("degree", "k"), [(-1, 16), (5, 36), (3, 9), (1, 3), (True, 4)])
def test_bad_sh_degree_names_it(degree: Any, k: int) -> None:
    t = sh_inputs((), 1, 8, k, seed=1, per_camera=False)
    with pytest.raises(ValueError, match=r"^sh_degree"):
        call(t, sh_degree=degree)


@pytest.mark.parametrize(
    ("shape", "sh_degree"),
    [((8, 3), 1), ((8, 4, 4), 1), ((5, 4, 3), 1), ((2, 8, 4, 3), 1), ((8, 4, 3, 1), None)],
)
def test_bad_colour_shapes_list_both_layouts(shape: tuple[int, ...], sh_degree: int | None) -> None:
    t = gsplat_inputs((), 1, 8, 3, seed=1, per_camera=False)
    t["colors"] = torch.rand(shape, dtype=torch.float64)
    with pytest.raises(
        ValueError, match=r"^colors: .*\[8, D\].*\[8, K, 3\]|^colors: .*\[8, K, 3\].*\[8, D\]"
    ):
        call(t, sh_degree=sh_degree)
