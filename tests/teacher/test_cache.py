"""TeacherFeatureCache: round trips, validation of corrupt entries, safe names, size on disk."""

from __future__ import annotations

import io
import os
import time
import uuid
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jaxtyping import TypeCheckError

from dego.teacher.cache import FORMAT_VERSION, TeacherFeatureCache


def _features(*shape: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _write_npz(path: Path, **arrays: np.ndarray) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    path.write_bytes(buffer.getvalue())


def _metadata(sample_id: str = "s", camera: int = 0, dtype: str = "float16") -> dict:
    return {
        "format_version": np.asarray(FORMAT_VERSION, dtype=np.int64),
        "dtype": np.asarray(dtype),
        "sample_id": np.asarray(sample_id),
        "camera": np.asarray(camera, dtype=np.int64),
    }


# -- round trips ----------------------------------------------------------------------
@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=25)
@given(
    st.integers(1, 5),
    st.integers(1, 4),
    st.integers(1, 4),
    st.floats(-14.0, 15.0),
    st.integers(0, 2**31 - 1),
)
def test_float16_round_trip_error_bound(
    tmp_path: Path, c: int, h: int, w: int, log2_scale: float, seed: int
) -> None:
    # Normal float16 range: |x| in [2^-14, 65504]. Relative rounding error <= 2^-11.
    cache = TeacherFeatureCache(tmp_path)
    magnitude = 2.0 ** (
        log2_scale
        + torch.rand(c, h, w, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        * 0.9
    )
    sign = torch.where(_features(c, h, w, seed=seed) > 0, 1.0, -1.0).double()
    x = (sign * magnitude).clamp(-65504, 65504)
    cache.save("sample", 3, x)
    y = cache.load("sample", 3, dtype=torch.float64)
    assert y.shape == (c, h, w) and y.dtype == torch.float64
    assert ((y - x).abs() <= 2.0**-11 * x.abs()).all()


def test_float64_to_float16_is_rounded_once(tmp_path: Path) -> None:
    # 1 + 2^-11 + 2^-40 rounds to 1 + 2^-10 directly, but to 1 via float32 (a tie to even).
    cache = TeacherFeatureCache(tmp_path)
    cache.save("s", 0, torch.full((1, 1, 1), 1 + 2.0**-11 + 2.0**-40, dtype=torch.float64))
    assert cache.load("s", 0).item() == 1 + 2.0**-10


def test_float32_round_trip_is_exact(tmp_path: Path) -> None:
    cache = TeacherFeatureCache(tmp_path, dtype=torch.float32)
    x = _features(8, 3, 5)
    path = cache.save("tok", 0, x)
    assert path == tmp_path / "tok_cam_0.npz" == cache.path("tok", 0)
    y = cache.load("tok", 0)
    assert y.dtype == torch.float32 and torch.equal(y, x)
    assert torch.equal(cache.load("tok", 0, dtype=torch.float64), x.double())


def test_default_load_is_float32_and_inputs_of_any_float_dtype(tmp_path: Path) -> None:
    cache = TeacherFeatureCache(tmp_path)
    for i, dtype in enumerate((torch.float16, torch.bfloat16, torch.float32, torch.float64)):
        x = _features(2, 3, 4, seed=i).to(dtype)
        x.requires_grad_(True)
        cache.save("s", i, x)
        y = cache.load("s", i, expected_shape=(2, 3, 4))
        assert y.dtype == torch.float32 and not y.requires_grad
        torch.testing.assert_close(y, x.detach().float(), rtol=2.0**-11, atol=0)


def test_devices(tmp_path: Path, device: torch.device) -> None:
    cache = TeacherFeatureCache(tmp_path)
    x = _features(2, 3, 4)
    cache.save("s", 0, x.to(device))
    y = cache.load("s", 0, device=device, dtype=torch.float16)
    assert y.device.type == device.type and y.dtype == torch.float16
    torch.testing.assert_close(y.cpu().float(), x, rtol=2.0**-11, atol=0)


def test_contains_keys_nbytes_overwrite(tmp_path: Path) -> None:
    cache = TeacherFeatureCache(tmp_path / "deep" / "dir")
    assert ("a", 0) not in cache and cache.keys() == []
    cache.save("a", 0, _features(2, 2, 2))
    cache.save("a_cam_1", 2, _features(2, 2, 2))
    cache.save("b", 1, _features(4, 2, 2))
    assert ("a", 0) in cache and ("a", 1) not in cache and ("b", 1) in cache
    assert cache.keys() == [("a", 0), ("a_cam_1", 2), ("b", 1)]
    assert cache.nbytes("b", 1) == cache.path("b", 1).stat().st_size > cache.nbytes("a", 0)
    cache.save("a", 0, _features(3, 2, 2, seed=5))  # atomic overwrite
    assert cache.load("a", 0).shape == (3, 2, 2)
    assert not [p for p in cache.root.iterdir() if p.name.startswith(".")]  # no temp files
    assert "float16" in repr(cache)


def test_opening_removes_stale_temporaries_of_interrupted_saves(tmp_path: Path) -> None:
    """A save killed before its os.replace leaves ``.<entry>.<hex>.tmp`` (issue 26): opening
    the cache removes those older than an hour and keeps younger ones (a save still running
    in another process) and anything else."""
    cache = TeacherFeatureCache(tmp_path)
    entry = cache.save("s", 0, _features(2, 3, 4))
    hour_ago = time.time() - 3600 - 60

    def temporary(name: str, *, old: bool) -> Path:
        path = tmp_path / f".{name}.{uuid.uuid4().hex}.tmp"
        path.write_bytes(b"\0" * 1024)
        if old:
            os.utime(path, (hour_ago, hour_ago))
        return path

    stale = [temporary("s_cam_0.npz", old=True), temporary("other_cam_12.npz", old=True)]
    fresh = temporary("s_cam_1.npz", old=False)
    kept = [
        tmp_path / ".notes.tmp",  # not a cache temporary
        tmp_path / f"s_cam_0.npz.{uuid.uuid4().hex}.tmp",  # not hidden: not write_npz's name
        tmp_path / f".data.npz.{uuid.uuid4().hex}.tmp",  # not an entry's name
    ]
    for path in kept:
        path.write_bytes(b"x")
        os.utime(path, (hour_ago, hour_ago))
    directory = tmp_path / f".s_cam_2.npz.{uuid.uuid4().hex}.tmp"
    directory.mkdir()
    os.utime(directory, (hour_ago, hour_ago))

    reopened = TeacherFeatureCache(tmp_path)
    assert not any(path.exists() for path in stale)
    assert fresh.exists() and all(path.exists() for path in kept) and directory.is_dir()
    assert entry.exists() and reopened.keys() == [("s", 0)]
    assert reopened.load("s", 0).shape == (2, 3, 4)
    TeacherFeatureCache(tmp_path / "not-yet-created")  # nothing to clean: no error


def test_features_of_another_shape_are_refused_from_the_header(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With ``expected_shape``, an entry declaring another (say huge) shape is refused from
    its ``.npy`` header, before anything is inflated (issue 26)."""
    cache = TeacherFeatureCache(tmp_path)
    path = cache.save("s", 0, _features(2, 3, 4))
    calls = []
    monkeypatch.setattr(np.lib.format, "read_array", lambda *a, **k: calls.append(a))
    with pytest.raises(ValueError, match=r"features: shape \(2, 3, 4\), expected_shape is") as e:
        cache.load("s", 0, expected_shape=(2048, 18, 50))
    assert calls == [] and str(path) in str(e.value)


# -- errors ---------------------------------------------------------------------------
def test_missing_entry(tmp_path: Path) -> None:
    cache = TeacherFeatureCache(tmp_path / "never-created")
    with pytest.raises(FileNotFoundError, match="sample 'tok' camera 4"):
        cache.load("tok", 4)
    with pytest.raises(FileNotFoundError, match="sample 'tok' camera 4"):
        cache.nbytes("tok", 4)


@pytest.mark.parametrize(
    "sample_id", ["", ".", "..", "../x", "a/b", "a\\b", ".hidden", "a..b", "a\x00b", "x" * 201]
)
def test_unsafe_sample_ids_are_rejected(tmp_path: Path, sample_id: str) -> None:
    cache = TeacherFeatureCache(tmp_path)
    for call in (
        lambda: cache.save(sample_id, 0, _features(1, 1, 1)),
        lambda: cache.load(sample_id, 0),
        lambda: cache.path(sample_id, 0),
        lambda: (sample_id, 0) in cache,
    ):
        with pytest.raises(ValueError, match=r"sample_id: .* is not a safe file name"):
            call()
    assert list(tmp_path.iterdir()) == []


def test_bad_arguments(tmp_path: Path) -> None:
    for dtype in (torch.bfloat16, torch.float64, torch.int8):
        with pytest.raises(ValueError, match=r"dtype: expected torch.float16 or torch.float32"):
            TeacherFeatureCache(tmp_path, dtype=dtype)
    with pytest.raises(TypeError, match="root"):
        TeacherFeatureCache(3)  # type: ignore[arg-type]
    cache = TeacherFeatureCache(tmp_path)
    with pytest.raises(ValueError, match="camera: expected an int >= 0"):
        cache.save("s", -1, _features(1, 1, 1))
    with pytest.raises(ValueError, match="camera: expected an int >= 0"):
        cache.path("s", True)
    with pytest.raises(TypeCheckError, match="parameter 'features'"):
        cache.save("s", 0, _features(1, 2, 3, 4))
    with pytest.raises(TypeCheckError, match="parameter 'features'"):
        cache.save("s", 0, torch.ones(1, 2, 3, dtype=torch.long))
    with pytest.raises(TypeCheckError, match="parameter 'key'"):
        ("s",) in cache  # noqa: B015
    cache.save("s", 0, _features(1, 2, 3))
    with pytest.raises(ValueError, match="expected_shape: expected 3 ints >= 1"):
        cache.load("s", 0, expected_shape=(1, 0, 3))
    with pytest.raises(ValueError, match="dtype: expected a floating dtype"):
        cache.load("s", 0, dtype=torch.int32)


def test_nonfinite_and_out_of_range_values_are_rejected_on_save(tmp_path: Path) -> None:
    cache = TeacherFeatureCache(tmp_path)
    x = _features(2, 2, 2)
    x[0, 1, 1] = 70000.0
    with pytest.raises(ValueError, match=r"features: .*70000.*exceed float16's range"):
        cache.save("s", 0, x)
    TeacherFeatureCache(tmp_path, dtype=torch.float32).save("s", 1, x)  # fine in float32
    with pytest.raises(ValueError, match=r"features: .*exceed float32's range"):
        TeacherFeatureCache(tmp_path, dtype=torch.float32).save(
            "s", 2, torch.full((1, 1, 1), 1e39, dtype=torch.float64)
        )
    x[0, 1, 1] = float("nan")
    with pytest.raises(ValueError, match="features: holds NaN or inf"):
        cache.save("s", 0, x)
    assert ("s", 0) not in cache


def test_shape_and_dtype_mismatch_on_load(tmp_path: Path) -> None:
    TeacherFeatureCache(tmp_path, dtype=torch.float32).save("s", 0, _features(2, 3, 4))
    path = tmp_path / "s_cam_0.npz"
    with pytest.raises(ValueError, match=f"{path}.*float32.*differs from this cache's float16"):
        TeacherFeatureCache(tmp_path).load("s", 0)
    with pytest.raises(ValueError, match=r"shape \(2, 3, 4\), expected_shape is \(2, 3, 5\)"):
        TeacherFeatureCache(tmp_path, dtype=torch.float32).load("s", 0, expected_shape=(2, 3, 5))


def _corrupt(kind: str, path: Path, payload: bytes) -> None:
    good = path.read_bytes()
    features = np.ones((2, 3, 4), dtype=np.float16)
    if kind == "truncated":
        path.write_bytes(good[: len(good) // 2])
    elif kind == "truncated_tail":
        path.write_bytes(good[:-10])
    elif kind == "garbage":
        path.write_bytes(b"not an npz file at all" * 10)
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "npy":
        buffer = io.BytesIO()
        np.save(buffer, features)
        path.write_bytes(buffer.getvalue())
    elif kind == "pickle":
        buffer = io.BytesIO()
        np.savez(buffer, features=np.array([{"a": 1}], dtype=object), **_metadata())
        path.write_bytes(buffer.getvalue())
    elif kind == "flipped_byte":
        data = bytearray(good)
        data[good.index(payload) + 5] ^= 0x01  # one bit of one stored value: CRC mismatch
        path.write_bytes(bytes(data))
    elif kind == "no_features":
        _write_npz(path, **_metadata())
    elif kind == "no_metadata":
        _write_npz(path, features=features)
    elif kind == "wrong_dtype":
        _write_npz(path, features=features.astype(np.float32), **_metadata())
    elif kind == "wrong_ndim":
        _write_npz(path, features=features[0], **_metadata())
    elif kind == "nan":
        bad = features.copy()
        bad[0, 0, 0] = np.nan
        _write_npz(path, features=bad, **_metadata())
    elif kind == "other_key":
        _write_npz(path, features=features, **_metadata(sample_id="t"))
    elif kind == "other_camera":
        _write_npz(path, features=features, **_metadata(camera=5))
    elif kind == "future_version":
        meta = _metadata()
        meta["format_version"] = np.asarray(FORMAT_VERSION + 1)
        _write_npz(path, features=features, **meta)
    elif kind == "not_a_zip_member":
        with zipfile.ZipFile(path, "w") as archive:
            for name, value in _metadata().items():
                buffer = io.BytesIO()
                np.save(buffer, value)
                archive.writestr(f"{name}.npy", buffer.getvalue())
            archive.writestr("features.npy", b"\x93NUMPY garbage header")
    else:
        raise AssertionError(kind)


@pytest.mark.parametrize(
    ("kind", "match"),
    [
        ("truncated", "not a readable .npz"),
        ("truncated_tail", "not a readable .npz"),
        ("garbage", "is not a zip archive"),
        ("empty", "is empty"),
        ("npy", "holds a single .npy array"),
        ("pickle", "allow_pickle=False"),
        ("flipped_byte", "cannot read array 'features'"),
        ("no_features", r"missing array\(s\) \['features'\]"),
        ("no_metadata", "missing array"),
        ("wrong_dtype", "stored dtype float32"),
        ("wrong_ndim", r"must be \(C, H, W\)"),
        ("nan", "NaN or inf"),
        ("other_key", "holds sample 't'"),
        ("other_camera", "camera 5"),
        ("future_version", "format_version 2"),
        ("not_a_zip_member", "cannot read array 'features'"),
    ],
)
def test_corrupted_entries_raise_value_error_naming_the_path(
    tmp_path: Path, kind: str, match: str
) -> None:
    cache = TeacherFeatureCache(tmp_path)
    features = _features(2, 3, 4)
    path = cache.save("s", 0, features)
    _corrupt(kind, path, features.half().numpy().tobytes())
    with pytest.raises(ValueError, match=match) as info:
        cache.load("s", 0)
    assert str(path) in str(info.value)


# -- size on disk ---------------------------------------------------------------------
def test_size_factor_against_the_official_layout(tmp_path: Path) -> None:
    """One VGGT block-22 map (2048, 18, 50) per (sample, camera), as the official cache."""
    features = _features(2048, 18, 50)
    ours = TeacherFeatureCache(tmp_path / "ours").save("tok", 0, features).stat().st_size
    official = tmp_path / "sample_tok_cam_0.pt"
    torch.save({"features": [features.float()[None]], "img": torch.zeros(3, 252, 700)}, official)
    factor = official.stat().st_size / ours
    assert ours < 2048 * 18 * 50 * 2 + 4096  # the float16 map plus small metadata
    assert factor >= 2.0, factor
    assert 2.4 < factor < 2.7  # ~9.49 MB / ~3.69 MB = 2.57


@pytest.mark.parametrize("key", ["format_version", "camera", "dtype", "sample_id"])
def test_metadata_must_be_scalars_from_the_header(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, key: str
) -> None:
    """Refused from the ``.npy`` header, before any member is inflated."""
    cache = TeacherFeatureCache(tmp_path)
    path = cache.save("s", 0, _features(2, 3, 4))
    with np.load(path) as stored:
        arrays = {name: stored[name] for name in stored.files}
    arrays[key] = np.stack([arrays[key], arrays[key]])
    np.savez(path, **arrays)
    calls = []
    monkeypatch.setattr(np.lib.format, "read_array", lambda *a, **k: calls.append(a))
    with pytest.raises(ValueError, match=rf"{key}: expected a scalar"):
        cache.load("s", 0)
    assert calls == []
