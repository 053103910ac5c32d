"""The restricted unpickler (dego.data.load_pickle) and mmdet3d infos -> Keyframe (load_infos)."""

from __future__ import annotations

import builtins
import codecs
import collections
import io
import os
import pickle
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import dego
from dego.data import Keyframe, UnsafePickleError, load_infos, load_pickle
from tests.helpers.nuscenes_fixtures import make_frames, matrix, write_infos

# ----------------------------------------------------------------------------------------
# load_pickle: what real files hold comes back
# ----------------------------------------------------------------------------------------


def _sample_data() -> dict[str, Any]:
    return {
        "infos": [
            {
                "token": "abc",
                "translation": [1.0, 2.0, 3.0],
                "rotation": (1.0, 0.0, 0.0, 0.0),
                "matrix": np.arange(12.0).reshape(3, 4),
                "fortran": np.asfortranarray(np.arange(6, dtype=np.float32).reshape(2, 3)),
                "strided": np.arange(10)[::3],
                "names": np.array(["car", "truck"]),
                "flags": np.array([True, False]),
                "score": np.float64(0.25),
                "count": np.int64(7),
                "half": np.float16(1.5),
                "records": np.zeros(2, dtype=[("x", "<f4"), ("y", "<i2", (2,))]),
                "objects": np.array([1, "a", np.ones(2)], dtype=object),
                "nested": {"sweeps": [{"t": 1}, {"t": 2}], "empty": {}, "none": None},
            }
        ],
        "metadata": collections.OrderedDict(version="v1.0-trainval"),
        "misc": {
            "set": {1, 2},
            "frozen": frozenset({"a"}),
            "bytes": b"\x00\xff",
            "no_bytes": b"",
            "bytearray": bytearray(b"xy"),
            "complex": 1 + 2j,
            "slice": slice(1, 9, 2),
            "range": range(3),
            "big": 2**100,
            "dtype": np.dtype("<f8"),
            "counts": collections.defaultdict(list, {"a": [1]}),
        },
    }


def _assert_same(a: Any, b: Any) -> None:
    assert type(a) is type(b), (type(a), type(b))
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape
        if a.dtype == object:
            for x, y in zip(a.ravel(), b.ravel(), strict=True):
                _assert_same(x, y)
        else:
            assert a.tobytes() == b.tobytes()
    elif isinstance(a, dict):
        assert list(a) == list(b)
        for key in a:
            _assert_same(a[key], b[key])
    elif isinstance(a, list | tuple):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y)
    else:
        assert a == b


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_load_pickle_round_trips_real_info_content(tmp_path: Path, protocol: int) -> None:
    data = _sample_data()
    path = tmp_path / "infos.pkl"
    path.write_bytes(pickle.dumps(data, protocol=protocol))
    loaded = load_pickle(path)
    _assert_same(data, loaded)
    assert loaded["misc"]["counts"].default_factory is list
    assert type(loaded["infos"][0]["objects"][2]) is np.ndarray
    assert isinstance(load_pickle(str(path)), dict)  # str paths too


def test_load_pickle_reads_numpy_1x_names(tmp_path: Path) -> None:
    data = {"a": np.arange(4.0), "s": np.float64(2.5)}
    written = pickle.dumps(data, protocol=2)  # GLOBAL opcodes: text names
    if b"numpy._core.multiarray" in written:  # written by numpy 2: rename as numpy 1.x does
        written = written.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    assert b"numpy.core.multiarray" in written
    path = tmp_path / "numpy1.pkl"
    path.write_bytes(written)
    _assert_same(data, load_pickle(path))


_leaves = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=False)
    | st.text(max_size=8)
    | st.binary(max_size=8)
    | hnp.arrays(
        st.sampled_from([np.float32, np.float64, np.int64, np.uint8, np.bool_]),
        hnp.array_shapes(min_dims=0, max_dims=3, max_side=3),
    )
)
_plain = st.recursive(
    _leaves,
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.tuples(inner, inner)
        | st.dictionaries(st.text(max_size=5), inner, max_size=4)
    ),
    max_leaves=12,
)


@given(_plain, st.integers(2, 5))
def test_load_pickle_round_trips_any_plain_structure(data: Any, protocol: int) -> None:
    buffer = io.BytesIO(pickle.dumps(data, protocol=protocol))
    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"dego-hypothesis-{os.getpid()}.pkl"
    path.write_bytes(buffer.getvalue())
    try:
        _assert_same(data, load_pickle(path))
    finally:
        path.unlink()


# ----------------------------------------------------------------------------------------
# load_pickle: nothing in the file runs
# ----------------------------------------------------------------------------------------


class _Reduce:
    def __init__(self, *reduced: Any) -> None:
        self.reduced = reduced

    def __reduce__(self) -> Any:
        return self.reduced


class Quaternion:  # stands in for pyquaternion.Quaternion: any class is refused
    def __init__(self) -> None:
        self.q = [1.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    "payload, name",
    [
        (lambda m: _Reduce(os.system, (f"touch {m}",)), f"{os.system.__module__}.system"),
        (lambda m: _Reduce(builtins.exec, (f"open({str(m)!r}, 'w').close()",)), "builtins.exec"),
        (lambda m: _Reduce(builtins.eval, (f"open({str(m)!r}, 'w')",)), "builtins.eval"),
        (lambda m: _Reduce(builtins.getattr, (dict, "fromkeys")), "builtins.getattr"),
        (lambda m: _Reduce(subprocess.Popen, (["touch", str(m)],)), "subprocess.Popen"),
        (lambda m: Quaternion(), "tests.data.test_infos.Quaternion"),
        (lambda m: _Reduce(codecs.encode, ("x", "rot13")), None),  # _codecs beyond latin-1
    ],
)
@pytest.mark.parametrize("protocol", [2, 4])
def test_load_pickle_refuses_every_other_global(
    tmp_path: Path, payload: Any, name: Any, protocol: int
) -> None:
    marker = tmp_path / "marker"
    path = tmp_path / "evil.pkl"
    data = {"infos": [{"token": "t", "x": payload(marker)}]}
    path.write_bytes(pickle.dumps(data, protocol=protocol))
    with pytest.raises(UnsafePickleError) as info:
        load_pickle(path)
    message = str(info.value)
    assert str(path) in message
    if name is not None:
        assert f"global {name}" in message and "numpy arrays are allowed" in message
    assert isinstance(info.value, pickle.UnpicklingError) and isinstance(info.value, ValueError)
    assert not marker.exists()


def test_load_pickle_refuses_globals_inside_object_arrays(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    array = np.array([1, _Reduce(os.system, (f"touch {marker}",))], dtype=object)
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"a": array}, protocol=4))
    with pytest.raises(UnsafePickleError, match=r"system"):
        load_pickle(path)
    assert not marker.exists()


def test_load_pickle_refuses_persistent_ids(tmp_path: Path) -> None:
    class Pickler(pickle.Pickler):
        def persistent_id(self, obj: Any) -> Any:
            return "storage-0" if obj == "secret" else None

    stream = io.BytesIO()
    Pickler(stream, protocol=2).dump({"k": "secret"})
    path = tmp_path / "persistent.pkl"
    path.write_bytes(stream.getvalue())
    with pytest.raises(UnsafePickleError, match=r"persistent id 'storage-0'"):
        load_pickle(path)


def test_load_pickle_never_calls_ndarray_on_raw_memory(tmp_path: Path) -> None:
    # np.ndarray((1,), object, buffer=...) would read the bytes as object pointers
    path = tmp_path / "ndarray.pkl"
    path.write_bytes(pickle.dumps(_Reduce(np.ndarray, ((1,), np.dtype(object), b"\x01" * 8))))
    with pytest.raises(UnsafePickleError, match=r"numpy.ndarray"):
        load_pickle(path)


def test_load_pickle_rebuilds_dtypes_before_arrays_use_them(tmp_path: Path) -> None:
    # a pickled dtype state may put a field past the item size (out-of-bounds reads)
    dtype_state = (3, "|", None, ("a",), {"a": (np.dtype("<f8"), 100_000)}, 8, 1, 16)
    dtype = _Reduce(np.dtype, ("V8", False, True), dtype_state)
    rebuild = np.arange(1).__reduce__()[0]  # numpy's _reconstruct
    array = _Reduce(rebuild, (np.ndarray, (0,), b"b"), (1, (1,), dtype, False, b"\x00" * 8))
    path = tmp_path / "dtype.pkl"
    path.write_bytes(pickle.dumps({"a": array}, protocol=2))
    with pytest.raises(ValueError, match=r"dtype") as info:
        load_pickle(path)
    assert str(path) in str(info.value)


def test_load_pickle_corrupt_and_missing_files(tmp_path: Path) -> None:
    good = pickle.dumps({"infos": [{"a": np.arange(100.0)}]}, protocol=4)
    for name, data in [
        ("truncated.pkl", good[: len(good) // 2]),
        ("empty.pkl", b""),
        ("garbage.pkl", b"this is not a pickle at all"),
    ]:
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(ValueError, match=name) as info:
            load_pickle(path)
        assert not isinstance(info.value, UnsafePickleError)
    with pytest.raises(FileNotFoundError, match=r"nope\.pkl"):
        load_pickle(tmp_path / "nope.pkl")


# ----------------------------------------------------------------------------------------
# load_infos
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def frames() -> list[Any]:
    return make_frames(seed=3, lengths=(6, 4))


def _check_keyframes(keyframes: tuple[Keyframe, ...], frames: list[Any], scene: Any) -> None:
    assert [k.token for k in keyframes] == [f.token for f in frames]
    for k, f in zip(keyframes, frames, strict=True):
        assert isinstance(k, Keyframe)
        assert k.scene == scene(f)
        assert k.timestamp == f.timestamp and type(k.timestamp) is int
        for got, want in (
            (k.lidar2ego, matrix(f.lidar_t, f.lidar_q)),
            (k.ego2global, matrix(f.ego_t, f.ego_q)),
        ):
            assert got.dtype == torch.float64 and got.shape == (4, 4)
            np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-9)


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_load_infos_reads_mmdet3d_0x_infos(
    tmp_path: Path, frames: list[Any], protocol: int
) -> None:
    path = write_infos(tmp_path / "nuscenes_infos_val.pkl", frames, protocol=protocol)
    _check_keyframes(load_infos(path), frames, lambda f: f.scene_name)
    assert dego.load_infos is load_infos


def test_load_infos_scene_fallbacks_and_layouts(tmp_path: Path, frames: list[Any]) -> None:
    path = write_infos(tmp_path / "a.pkl", frames, scene_keys=("scene_token",))
    _check_keyframes(load_infos(path), frames, lambda f: f.scene_token)
    path = write_infos(tmp_path / "b.pkl", frames, scene_keys=())
    _check_keyframes(load_infos(path), frames, lambda f: "")
    path = write_infos(tmp_path / "c.pkl", frames, layout="bare")
    _check_keyframes(load_infos(path), frames, lambda f: f.scene_name)
    path = write_infos(tmp_path / "d.pkl", frames, layout="data_list", protocol=4)
    _check_keyframes(load_infos(path), frames, lambda f: "")


def test_load_infos_normalises_quaternions(tmp_path: Path, frames: list[Any]) -> None:
    infos = [_info(frames[0])]
    infos[0]["ego2global_rotation"] = [2.5 * v for v in frames[0].ego_q]
    infos[0]["lidar2ego_rotation"] = np.array([-0.3 * v for v in frames[0].lidar_q])  # -q too
    (kf,) = load_infos(_dump(tmp_path / "q.pkl", {"infos": infos}))
    np.testing.assert_allclose(
        kf.ego2global.numpy(), matrix(frames[0].ego_t, frames[0].ego_q), atol=1e-12
    )
    np.testing.assert_allclose(
        kf.lidar2ego.numpy(), matrix(frames[0].lidar_t, frames[0].lidar_q), atol=1e-12
    )


def _info(frame: Any) -> dict[str, Any]:
    return {
        "token": frame.token,
        "timestamp": frame.timestamp,
        "scene_name": frame.scene_name,
        "lidar2ego_translation": list(frame.lidar_t),
        "lidar2ego_rotation": list(frame.lidar_q),
        "ego2global_translation": list(frame.ego_t),
        "ego2global_rotation": list(frame.ego_q),
    }


def _dump(path: Path, data: Any) -> Path:
    path.write_bytes(pickle.dumps(data, protocol=2))
    return path


@pytest.mark.parametrize(
    "edit, pattern",
    [
        (
            lambda i: i[1].pop("ego2global_rotation"),
            r"infos\[1\]: missing key 'ego2global_rotation'",
        ),
        (lambda i: i[2].pop("token"), r"infos\[2\]: missing key 'token'"),
        (
            lambda i: i[1].update(ego2global_translation=[1.0, np.nan, 0.0]),
            r"infos\[1\]: ego2global_translation: holds non-finite",
        ),
        (
            lambda i: i[0].update(lidar2ego_rotation=[1.0, 0.0, 0.0]),
            r"infos\[0\]: lidar2ego_rotation: expected shape \(4,\)",
        ),
        (
            lambda i: i[0].update(lidar2ego_translation="0.9 0 1.8"),
            r"infos\[0\]: lidar2ego_translation: expected 3 numbers",
        ),
        (
            lambda i: i[3].update(ego2global_rotation=[0.0, 0.0, 0.0, 0.0]),
            r"infos\[3\]: ego2global_rotation: .*norm 0",
        ),
        (
            lambda i: i[2].update(token=i[0]["token"]),
            r"duplicate token '.+' in infos\[0\] and infos\[2\]",
        ),
        (lambda i: i[1].update(timestamp="noon"), r"infos\[1\]: timestamp"),
        (lambda i: i.__setitem__(1, ["not", "a", "dict"]), r"infos\[1\]: expected a dict"),
        (lambda i: i.clear(), r"empty"),
    ],
)
def test_load_infos_bad_entries_name_file_entry_and_field(
    tmp_path: Path, frames: list[Any], edit: Any, pattern: str
) -> None:
    infos = [_info(f) for f in frames[:4]]
    edit(infos)
    path = _dump(tmp_path / "bad.pkl", {"infos": infos, "metadata": {}})
    with pytest.raises(ValueError, match=pattern) as info:
        load_infos(path)
    assert str(path) in str(info.value)


def test_load_infos_bad_layouts(tmp_path: Path, frames: list[Any]) -> None:
    with pytest.raises(ValueError, match=r"'infos'.*'data_list'"):
        load_infos(_dump(tmp_path / "a.pkl", {"samples": []}))
    with pytest.raises(ValueError, match=r"data_list\[0\]: missing key 'lidar_points.lidar2ego'"):
        load_infos(
            _dump(
                tmp_path / "b.pkl",
                {
                    "data_list": [
                        {
                            "token": "t",
                            "timestamp": 1.0,
                            "ego2global": np.eye(4).tolist(),
                            "lidar_points": {},
                        }
                    ]
                },
            )
        )
    bad = np.eye(4)
    bad[3, 0] = 2.0
    with pytest.raises(ValueError, match=r"data_list\[0\]: ego2global: last row"):
        load_infos(
            _dump(
                tmp_path / "c.pkl",
                {
                    "data_list": [
                        {
                            "token": "t",
                            "timestamp": 1.0,
                            "ego2global": bad,
                            "lidar_points": {"lidar2ego": np.eye(4)},
                        }
                    ]
                },
            )
        )
    with pytest.raises(UnsafePickleError):
        load_infos(_dump(tmp_path / "d.pkl", [_Reduce(os.system, ("true",))]))
    with pytest.raises(FileNotFoundError, match=r"absent\.pkl"):
        load_infos(tmp_path / "absent.pkl")


# -- issue 38 (3): what a few bytes can make the loader allocate ------------------------

BOMBS = {
    # LONG_BINPUT 2**31: the C unpickler grew its memo array to 2**31 entries (16 GB)
    "memo": b"\x80\x02Nr\x00\x00\x00\x80.",
    "bytes": b"cbuiltins\nbytes\n(\x8a\x05\x00\x00\x00\x00\x10tR.",  # bytes(2**36)
    "bytearray": b"cbuiltins\nbytearray\n(\x8a\x05\x00\x00\x00\x00\x01tR.",  # 2**32
    "list": b"cbuiltins\nlist\n(cbuiltins\nrange\n(J\x00\xca\x9a;tRtR.",  # range(10**9)
    "set": b"cbuiltins\nset\n(cbuiltins\nrange\n(J\x00-1\x01tRtR.",  # range(2 * 10**7)
    "newobj": b"\x80\x02cbuiltins\nbytes\n\x8a\x05\x00\x00\x00\x00\x10\x85\x81.",
    "binbytes8": b"\x80\x04\x8e\x00\x00\x00\x00\x00\x00\x00\x01.",  # 2**56 bytes declared
}

BOMB_CHECK = r"""
import json, resource, sys, tracemalloc
from pathlib import Path
resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))  # a regression fails, not the machine
from dego.data import UnsafePickleError, load_pickle
import pickle
benign = Path(sys.argv[1]).with_name("benign.pkl")
benign.write_bytes(pickle.dumps({"a": [1, 2.0]}))
load_pickle(benign)  # first use builds the argument checks (beartype): not the file's doing
results = {}
for path in sys.argv[1:]:
    tracemalloc.start()
    try:
        value = load_pickle(path)
        outcome = f"loaded {value!r}"
    except UnsafePickleError as exc:
        outcome = f"refused: {exc}"
    except ValueError as exc:
        outcome = f"unreadable: {exc}"
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    results[Path(path).stem] = [outcome, peak, Path(path).stat().st_size]
print(json.dumps(results))
"""


@pytest.mark.slow
def test_a_hostile_file_cannot_make_the_loader_allocate_much(tmp_path: Path) -> None:
    """Issue 38 (3): 10-40-byte files made load_pickle try to allocate gigabytes. Each is
    now refused (or, the memo index without numba, harmless) with memory growth under 10x the file size
    plus 1 MiB; the check runs in a subprocess under a 4 GiB address-space limit."""
    import json
    import subprocess
    import sys

    paths = []
    for name, payload in BOMBS.items():
        (tmp_path / f"{name}.pkl").write_bytes(payload)
        paths.append(str(tmp_path / f"{name}.pkl"))
    done = subprocess.run(
        [sys.executable, "-c", BOMB_CHECK, *paths], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    results = json.loads(done.stdout.strip().splitlines()[-1])
    # the compiled scan refuses the memo index; the pure-Python unpickler's memo is a dict
    assert results["memo"][0] == "loaded None" or "memo index far beyond" in results["memo"][0]
    for name in ("bytes", "bytearray", "newobj"):
        assert results[name][0].startswith("refused: ") and "size argument" in results[name][0]
    assert "list() of 1,000,000,000 items" in results["list"][0]
    assert "set() of 20,000,000 items" in results["set"][0]
    binbytes8 = results["binbytes8"][0]
    assert (
        "declares 72,057,594,037,927,936 bytes" in binbytes8 or "longer than the rest" in binbytes8
    )
    for name, (_, peak, size) in results.items():
        assert peak < 10 * size + (1 << 20), (name, peak)
