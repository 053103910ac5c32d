"""The Triton kernels' launch settings (:mod:`dego.splatting.triton_configs`): the table per
GPU family, the safe default with its one-time warnings, user entries and the opt-in
autotuner's configuration (built and inspected here, never run: tests never autotune)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from types import SimpleNamespace
from typing import Any

import pytest
import torch

from dego.splatting import triton_configs
from dego.splatting.triton_configs import SAFE, TABLE, LaunchConfig
from tests.helpers import triton


@pytest.fixture(autouse=True)
def _fresh_state(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(triton_configs, "TABLE", dict(TABLE))
    monkeypatch.setattr(triton_configs, "_warned", set())
    monkeypatch.setattr(triton_configs, "_unfit", set())
    monkeypatch.setattr(triton_configs, "_autotune", False)


def _gpu(monkeypatch: pytest.MonkeyPatch, *, major: int = 9, minor: int = 0, hip: str = "") -> None:
    """Pretend ``cuda:0`` is an NVIDIA sm_<major><minor> (or, with ``hip``, that AMD GPU)."""
    properties = SimpleNamespace(major=major, minor=minor, gcnArchName=hip)
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: properties)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device: "Test GPU")
    monkeypatch.setattr(torch.version, "hip", "6.2" if hip else None)


CUDA = torch.device("cuda", 0)


@pytest.mark.parametrize(
    ("major", "minor", "hip", "expected"),
    [
        (9, 0, "", "sm_90"),
        (8, 0, "", "sm_80"),
        (8, 9, "", "sm_89"),
        (0, 0, "gfx942:sramecc+:xnack-", "gfx942"),
    ],
)
def test_the_family_of_a_gpu(
    monkeypatch: pytest.MonkeyPatch, major: int, minor: int, hip: str, expected: str
) -> None:
    _gpu(monkeypatch, major=major, minor=minor, hip=hip)
    assert triton_configs.family(CUDA) == expected
    assert triton_configs.family(torch.device("cpu")) == "cpu"


def test_known_gpus_get_their_entry_without_a_warning(monkeypatch: pytest.MonkeyPatch) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for major, minor in ((9, 0), (8, 0)):
            _gpu(monkeypatch, major=major, minor=minor)
            assert triton_configs.config_for(CUDA) is TABLE[f"sm_{major}{minor}"]
        assert triton_configs.config_for(torch.device("cpu")) is TABLE["cpu"]


def test_an_unknown_gpu_gets_the_safe_default_and_one_warning(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _gpu(monkeypatch, major=8, minor=9)
    with pytest.warns(RuntimeWarning, match=r"no launch configuration for sm_89 \(Test GPU\)"):
        assert triton_configs.config_for(CUDA) is SAFE
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert triton_configs.config_for(CUDA) is SAFE  # warned once
    entry = LaunchConfig(forward_warps=4, pixels=32)
    triton_configs.set_launch_config("sm_89", entry)
    assert triton_configs.config_for(CUDA) is entry
    triton_configs.set_launch_config("sm_89", None)  # not shipped: removed again
    assert "sm_89" not in triton_configs.TABLE
    triton_configs.set_launch_config("sm_90", entry)
    triton_configs.set_launch_config("sm_90", None)  # shipped: restored
    assert triton_configs.TABLE["sm_90"] == LaunchConfig()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("forward_warps", 3),
        ("forward_warps", True),
        ("backward_warps", 64),
        ("channels", 8),
        ("pixels", 48),
        ("bucket", 512),
        ("bucket", 32.0),
        ("maxnreg", 16),
        ("maxnreg", 300),
    ],
)
def test_a_bad_setting_names_its_field(field: str, value: Any) -> None:
    with pytest.raises(ValueError, match=rf"^LaunchConfig: {field}: expected .*got {value!r}$"):
        LaunchConfig(**{field: value})


def test_set_launch_config_checks_its_arguments() -> None:
    with pytest.raises(ValueError, match=r"set_launch_config: name: expected a family"):
        triton_configs.set_launch_config("", LaunchConfig())
    with pytest.raises(TypeError, match=r"set_launch_config: config: expected a LaunchConfig"):
        triton_configs.set_launch_config("sm_89", {"pixels": 32})  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"autotune: enabled: expected a bool, got str"):
        triton_configs.autotune("yes")  # type: ignore[arg-type]


class _Kernel:
    """Stands in for a Triton kernel: records each launch's options; the first launch at
    other than the safe settings raises ``error``."""

    def __init__(self, error: Exception | None) -> None:
        self.error, self.launches = error, []

    def __getitem__(self, grid: Any) -> Any:
        def launch(*args: Any, **options: Any) -> None:
            self.launches.append(options)
            args[0].add_(1.0)  # an accumulated output
            if self.error is not None and options["BLOCK_P"] != SAFE.pixels:
                raise self.error

        return launch


def _launch(kernel: _Kernel, buffer: torch.Tensor) -> None:
    triton_configs.run(
        kernel,
        lambda meta: (1,),
        (buffer,),
        {"S": 16},
        device=torch.device("cpu"),
        bucket=16,
        zeroed=(buffer,),
    )


@pytest.mark.skipif(not triton.INSTALLED, reason=triton.NOT_INSTALLED)
def test_an_entry_that_does_not_fit_falls_back_to_the_safe_default_once() -> None:
    from triton.runtime.errors import OutOfResources

    kernel, buffer = _Kernel(OutOfResources(300_000, 232_448, "shared memory")), torch.zeros(3)
    with pytest.warns(RuntimeWarning, match=r"configuration for cpu does not fit cpu"):
        _launch(kernel, buffer)
    assert [o["BLOCK_P"] for o in kernel.launches] == [TABLE["cpu"].pixels, SAFE.pixels]
    assert all(o["BUCKET"] == 16 for o in kernel.launches)  # the forward's buckets kept
    assert torch.equal(buffer, torch.ones(3))  # zeroed before the second launch
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _launch(kernel, buffer)
    assert kernel.launches[-1]["BLOCK_P"] == SAFE.pixels  # remembered, warned once


def test_other_launch_errors_are_raised() -> None:
    kernel = _Kernel(RuntimeError("PassManager::run failed"))
    with pytest.raises(RuntimeError, match="PassManager"):
        _launch(kernel, torch.zeros(3))
    assert len(kernel.launches) == 1


@pytest.mark.skipif(not triton.INSTALLED, reason=triton.NOT_INSTALLED)
def test_the_autotuner_resets_every_buffer_the_backward_accumulates_into() -> None:
    """Every ``tl.atomic_add`` target of the backward (through its local aliases) is in
    ``reset_to_zero``, or the first autotuned backward would return the trials' sums."""
    import inspect

    from dego.splatting import triton_kernels

    source = inspect.getsource(triton_kernels)  # the kernels and their jit helpers
    aliases = dict(re.findall(r"(\w+) = (\w+_ptr)\b", source))
    targets = {aliases.get(t, t) for t in re.findall(r"tl\.atomic_add\(\s*(\w+)", source)}
    assert targets == {
        "grad_means_ptr",
        "grad_conics_ptr",
        "grad_opacities_ptr",
        "grad_colors_ptr",
        "absgrad_ptr",
    }
    assert set(triton_configs.ACCUMULATED) == targets
    tuned = triton_configs._autotuned(triton_kernels._backward_kernel, backward=True)
    assert set(tuned.reset_to_zero) == targets
    assert {c.kwargs["BLOCK_P"] for c in tuned.configs} == {32, 64, 128}
    assert tuned.keys == ["dim", "S", "SUMS"]
    forward = triton_configs._autotuned(triton_kernels._forward_kernel, backward=False)
    assert forward.reset_to_zero == []  # the forward only stores
    assert {c.kwargs["BLOCK_D"] for c in forward.configs} == {16, 32, 64}


def test_autotune_is_opt_in_and_never_on_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    assert not triton_configs.autotuning()
    triton_configs.autotune()
    assert triton_configs.autotuning()
    kernel, buffer = _Kernel(None), torch.zeros(3)
    _launch(kernel, buffer)  # the interpreter's CPU tensors: the table, not the autotuner
    assert kernel.launches[0]["BLOCK_P"] == TABLE["cpu"].pixels
    triton_configs.autotune(False)
    assert not triton_configs.autotuning()


def test_the_environment_turns_autotune_on_and_the_module_does_not_import_triton() -> None:
    code = (
        "import sys; from dego.splatting import triton_configs as c; "
        "print(c.autotuning(), 'triton' in sys.modules)"
    )
    for value, expected in (("1", "True False"), ("0", "False False")):
        env = {**os.environ, "DEGO_TRITON_AUTOTUNE": value}
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
        )
        assert done.stdout.split() == expected.split()


@pytest.mark.slow
@pytest.mark.skipif(triton.why_not("cpu") is not None, reason=triton.why_not("cpu") or "")
def test_the_autotuned_path_gives_the_tables_gradients(monkeypatch: pytest.MonkeyPatch) -> None:
    """The autotuner's path end to end in the interpreter, its timer replaced (nothing is
    timed; trials are ranked by a fixed rule): every trial runs the kernels into the same
    buffers, so without ``reset_to_zero`` the gradients would come back summed over the
    trials."""
    from tests.splatting import test_triton as cases

    scene = cases._deep_stack("cpu")
    table = cases._screen_gradients(scene, backend="triton")
    trials: list[int] = []

    def ranked(fn: Any, quantiles: Any = None, **kwargs: Any) -> list[float]:
        fn()
        trials.append(1)
        return [float(len(trials) % 5), 0.0, 0.0]

    build = triton_configs._autotuned

    def autotuned(kernel: Any, backward: bool) -> Any:
        tuned = build(kernel, backward)
        tuned.do_bench = ranked  # a fresh autotuner (``_tuned`` is emptied below)
        return tuned

    run = triton_configs.run

    def as_on_a_gpu(*args: Any, device: torch.device, **kwargs: Any) -> None:
        run(*args, device=torch.device("cuda"), **kwargs)  # the autotuner runs on CUDA only

    monkeypatch.setattr(triton_configs, "_tuned", {})
    monkeypatch.setattr(triton_configs, "_autotuned", autotuned)
    monkeypatch.setattr(triton_configs, "run", as_on_a_gpu)
    triton_configs.autotune()
    tuned = cases._screen_gradients(scene, backend="triton")
    assert len(trials) > 6  # every kernel tried several settings
    for name, grad in table.items():
        assert grad is not None
        assert cases._relative(tuned[name], grad) <= 1e-5, name
