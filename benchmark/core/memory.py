"""Peak memory of a run, and of the stages inside it.

A run's peak (:func:`reset_peak`, :func:`peak_cpu_mib`, :func:`peak_gpu_mib`) and the peak of each
stage of a fit (:class:`StagePeak`: geometry, autoencoder, field) are both wanted: a method that
reuses another method's cached geometry never runs that stage, yet needs the memory it took, just as
it is charged for its seconds (:func:`benchmark.results.fit_seconds_with_shared`). The stage's peak
is recorded beside its cached result, and the results tables charge it to every run that reuses it.

Linux keeps one high-water mark per process (``VmHWM``, reset by writing ``"5"`` to
``/proc/self/clear_refs``) and torch one per CUDA device. Measuring a stage restarts that mark, so
whatever it held before the restart is carried by every window still open (the run's and any
enclosing stage's): a window's peak is the largest of what it carried and the mark now. Where the
mark cannot be reset (not Linux), every peak is the process's peak so far: ``window()`` says which.
"""

from __future__ import annotations

import gc
import resource
import sys
from pathlib import Path
from typing import Optional

_PROC_STATUS = Path("/proc/self/status")
_PROC_CLEAR_REFS = Path("/proc/self/clear_refs")


class _Window:
    """What one open measurement carried from before the marks were last restarted (MiB)."""

    def __init__(self) -> None:
        self.cpu = 0.0
        self.gpu: dict[str, float] = {}


_run = _Window()
_open: list[_Window] = []  # stages being measured, outermost first
_resettable: Optional[bool] = None  # whether this process could restart the CPU mark (None: not tried)


def _status_mib(field: str) -> Optional[float]:
    """A size line of ``/proc/self/status`` (``VmHWM``, ``VmRSS``), MiB; None where the OS does not say."""
    try:
        for line in _PROC_STATUS.read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cpu_mark() -> float:
    """The kernel's high-water resident size, MiB (``getrusage`` maxrss where there is no ``VmHWM``)."""
    mark = _status_mib("VmHWM")
    if mark is not None:
        return mark
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform != "darwin" else rss / (1024.0 * 1024.0)


def _resident_mib() -> float:
    """The process's resident size now (``VmRSS``), MiB; NaN where the OS does not say."""
    now = _status_mib("VmRSS")
    return float("nan") if now is None else now


def _cuda_devices() -> list[str]:
    torch = sys.modules.get("torch")  # nothing to measure where torch is not loaded
    if torch is None or not torch.cuda.is_available() or not torch.cuda.is_initialized():
        return []
    return [f"cuda:{i}" for i in range(torch.cuda.device_count())]


def _gpu_mark(device: str) -> float:
    import torch

    return torch.cuda.max_memory_allocated(torch.device(device)) / 2 ** 20


def _restart_marks() -> bool:
    """Hand the marks' current values to every open window, then restart them. The CPU window starts
    at the current resident size, so memory freed earlier is first handed back to the OS (a garbage
    collection, then glibc's ``malloc_trim``): freed heap the allocator keeps would count as the new
    window's otherwise. Returns whether the CPU mark could be restarted."""
    global _resettable
    cpu = _cpu_mark()
    gpus = {d: _gpu_mark(d) for d in _cuda_devices()}
    for window in (_run, *_open):
        window.cpu = max(window.cpu, cpu)
        for d, v in gpus.items():
            window.gpu[d] = max(window.gpu.get(d, 0.0), v)
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to trim
        pass
    if gpus:
        import torch

        for d in gpus:
            torch.cuda.reset_peak_memory_stats(torch.device(d))
    try:
        _PROC_CLEAR_REFS.write_text("5")
        _resettable = True
    except OSError:
        _resettable = False
    return _resettable


def reset_peak() -> bool:
    """Start a new run's window (a ``run-all`` evaluates many runs in one process: a process-wide peak
    would charge a small method with the peak of a large one before it). Returns False where the CPU
    mark cannot be restarted: then :func:`peak_cpu_mib` is the process's peak so far."""
    global _run
    ok = _restart_marks()
    _run = _Window()  # what the previous run held is not this one's
    return ok


def window() -> str:
    """``"run"`` when peaks are this run's (or stage's) own, ``"process"`` where the OS kept one mark."""
    return "run" if _resettable else "process"


def peak_cpu_mib() -> float:
    """Peak resident memory of the current run, MiB (since :func:`reset_peak`)."""
    return max(_run.cpu, _cpu_mark())


def peak_gpu_mib(device: str) -> Optional[float]:
    """Peak CUDA memory allocated by torch on ``device`` in the current run, MiB; None off CUDA."""
    name = _cuda_name(device)
    return None if name is None else max(_run.gpu.get(name, 0.0), _gpu_mark(name))


def _cuda_name(device: str) -> Optional[str]:
    """``"cuda:<index>"`` of a CUDA ``device`` (the current one for a bare ``"cuda"``), as
    :func:`_cuda_devices` names them; None off CUDA."""
    if not str(device).startswith("cuda"):
        return None
    import torch

    if not torch.cuda.is_available():
        return None
    return str(torch.device(device)) if ":" in str(device) else f"cuda:{torch.cuda.current_device()}"


class StagePeak:
    """``with StagePeak(device) as peak: ...``: afterwards ``peak.cpu_mib`` (resident memory, MiB) and
    ``peak.gpu_mib`` (CUDA memory allocated on ``device``, MiB; None off CUDA) are the stage's own
    peaks; the run's peak and any enclosing stage's still include them. ``peak.baseline_cpu_mib`` is
    the resident size when the stage began (after freed memory went back to the OS; NaN where the OS
    does not say): the stage's own growth is ``cpu_mib - baseline_cpu_mib``, without what the process
    (interpreter, torch, the scene) held before. ``peak.record()`` is the dict a stage stores in its info."""

    def __init__(self, device: str = "cpu") -> None:
        self.device = str(device)
        self.cpu_mib: float = float("nan")
        self.gpu_mib: Optional[float] = None
        self.baseline_cpu_mib: float = float("nan")
        self._window: Optional[_Window] = None

    def __enter__(self) -> "StagePeak":
        _restart_marks()
        self.baseline_cpu_mib = _resident_mib()
        self._window = _Window()
        _open.append(self._window)
        return self

    def __exit__(self, *exc) -> None:
        window_ = self._window
        if window_ in _open:
            _open.remove(window_)
        self.cpu_mib = max(window_.cpu, _cpu_mark())
        name = _cuda_name(self.device)
        if name is not None:
            self.gpu_mib = max(window_.gpu.get(name, 0.0), _gpu_mark(name))

    def record(self) -> dict:
        return {"peak_cpu_mib": self.cpu_mib, "peak_gpu_mib": self.gpu_mib, "peak_window": window(),
                "baseline_cpu_mib": self.baseline_cpu_mib}


def available_memory_gb() -> float:
    """Memory the system can still give (``MemAvailable``), in GB (2^30 bytes); NaN where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / (1 << 20)
    except (OSError, ValueError, IndexError):
        pass
    return float("nan")
