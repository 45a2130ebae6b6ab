"""Generated scenes do not depend on which BLAS kernels the CPU gets: numpy's OpenBLAS is pinned to the
kernels the committed scene versions were made with (benchmark.core.openblas), in this process when bench4d
loads before numpy, else in a child process that the generator starts."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmark.core import openblas
from benchmark.synthetic.generate import generate
from benchmark.synthetic.digest import expected_digest, scene_digest

ROOT = Path(__file__).resolve().parents[1]


def _cpuinfo(tmp_path: Path, flags: str) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text(f"processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: {flags}\n\nprocessor\t: 1\n")
    return path


def test_cpuinfo_values_are_the_first_cpus(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: AMD EPYC 9B14\nflags\t\t: avx2 fma\n\n"
                    "processor\t: 1\nmodel name\t: other\n")
    assert openblas.cpuinfo_value("model name", info) == "AMD EPYC 9B14"
    assert openblas.cpuinfo_value("flags", info) == "avx2 fma"
    assert openblas.cpuinfo_value("microcode", info) is None
    assert openblas.cpuinfo_value("model name", tmp_path / "absent") is None


def test_the_pinned_kernels_need_avx2_and_fma(tmp_path, monkeypatch):
    monkeypatch.setattr(openblas.platform, "machine", lambda: "x86_64")
    assert openblas.cpu_runs_pinned_core(_cpuinfo(tmp_path, "fpu sse2 avx avx2 fma avx512f"))
    assert not openblas.cpu_runs_pinned_core(_cpuinfo(tmp_path, "fpu sse2 avx fma"))  # no AVX2: would fault
    assert not openblas.cpu_runs_pinned_core(tmp_path / "absent")
    monkeypatch.setattr(openblas.platform, "machine", lambda: "aarch64")
    assert not openblas.cpu_runs_pinned_core(_cpuinfo(tmp_path, "avx2 fma"))


def test_the_pin_is_set_only_before_numpy_loads_and_never_over_a_users_choice(monkeypatch):
    monkeypatch.setattr(openblas, "cpu_runs_pinned_core", lambda: True)
    monkeypatch.delenv(openblas.CORE_VARIABLE, raising=False)
    assert "numpy" in sys.modules and openblas.pin_before_numpy() is False  # too late: OpenBLAS has loaded
    assert openblas.CORE_VARIABLE not in os.environ
    monkeypatch.delitem(sys.modules, "numpy")
    monkeypatch.setenv(openblas.CORE_VARIABLE, "Zen")
    assert openblas.pin_before_numpy() is False and os.environ[openblas.CORE_VARIABLE] == "Zen"
    monkeypatch.delenv(openblas.CORE_VARIABLE)
    assert openblas.pin_before_numpy() is True and os.environ[openblas.CORE_VARIABLE] == openblas.PINNED_CORE


def test_a_child_is_needed_only_off_the_reference_kernels_where_they_can_run(monkeypatch):
    monkeypatch.delenv(openblas.CHILD_FLAG, raising=False)
    monkeypatch.setattr(openblas, "cpu_runs_pinned_core", lambda: True)
    for core, needed in (("skylakex", True), ("haswell", False), ("zen", False), (None, False)):
        monkeypatch.setattr(openblas, "openblas_core", lambda core=core: core)
        assert openblas.generation_needs_pinned_process() is needed, core
    monkeypatch.setattr(openblas, "openblas_core", lambda: "skylakex")
    monkeypatch.setenv(openblas.CHILD_FLAG, "1")  # the child itself never starts another
    assert openblas.generation_needs_pinned_process() is False
    monkeypatch.delenv(openblas.CHILD_FLAG)
    monkeypatch.setattr(openblas, "cpu_runs_pinned_core", lambda: False)  # cannot run them: nothing to gain
    assert openblas.generation_needs_pinned_process() is False


def test_this_process_reads_the_core_numpy_runs():
    core = openblas.openblas_core()
    assert core is None or (core.isascii() and core == core.lower() and core.strip() == core and core)
    if core is not None and openblas.cpu_runs_pinned_core():
        assert core in openblas.REFERENCE_CORES  # conftest imports bench4d before numpy: pinned here


def test_the_generator_in_a_pinned_child_makes_the_committed_scene(tmp_path, monkeypatch):
    monkeypatch.setattr(openblas, "generation_needs_pinned_process", lambda: True)
    out = generate("smoke", tmp_path / "smoke", size=48)
    assert scene_digest(out) == expected_digest("smoke", 48)
    with pytest.raises(Exception, match="not empty"):  # the parent still checks its arguments first
        generate("smoke", out, size=48)


def test_a_script_that_loads_numpy_before_bench4d_still_makes_the_committed_scene(tmp_path):
    """Where numpy loads first on a CPU with other kernels (AVX-512) the generator renders in a pinned
    child; elsewhere in this process. Either way the committed version comes out."""
    env = {k: v for k, v in os.environ.items() if k not in (openblas.CORE_VARIABLE, openblas.CHILD_FLAG)}
    code = ("import numpy, sys; from benchmark.core import openblas; from benchmark.synthetic import generate; "
            "from benchmark.synthetic.digest import scene_digest; "
            "print(openblas.openblas_core(), openblas.generation_needs_pinned_process(), "
            "scene_digest(generate('smoke', sys.argv[1], size=48)))")
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "smoke")], env=env, cwd=ROOT,
                          capture_output=True, text=True, check=True)
    core, needed, digest = done.stdout.split()
    assert digest == expected_digest("smoke", 48), (core, needed)


def test_a_failing_child_is_reported_with_the_preset_and_the_folder(tmp_path, monkeypatch):
    generate_module = importlib.import_module("benchmark.synthetic.generate")  # the module, not the function

    monkeypatch.setattr(openblas, "generation_needs_pinned_process", lambda: True)
    monkeypatch.setattr(generate_module.sys, "executable", "/bin/false")  # a child that exits 1
    with pytest.raises(RuntimeError, match=r"'smoke' into .*broken.*\(exit status 1\)"):
        generate("smoke", tmp_path / "broken", size=48)
    assert not (tmp_path / "broken").exists()  # nothing half-written
