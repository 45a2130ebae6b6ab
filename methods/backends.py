"""The real track's model backends: what each is, where its weights come from, and whether they are here.

Each backend loads from a local folder (an environment variable or an option names it) or, where the
library supports it, from a hub id through the Hugging Face cache on the user's machine. bench4d never
downloads weights itself: ``bench4d models`` says what is present and where it looked.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional


@dataclass(frozen=True)
class Backend:
    """One real model of the paper's pipeline."""

    name: str
    """Short name, e.g. ``"clip"``."""
    role: str
    """What the pipeline uses it for."""
    model: str
    """The paper's model, as its authors name it."""
    hub_id: Optional[str]
    """Hugging Face hub id of the weights bench4d loads (``None``: a local file only)."""
    env: str
    """Environment variable naming a local folder or file of the weights (it wins over the hub id)."""
    size_gb: float
    """Approximate size of the weights on disk, GB."""
    gpu_memory_gb: float
    """Approximate GPU memory to run it in the precision bench4d uses, GB."""
    extra: str
    """The pip extra that installs its library: ``pip install 'bench4d[<extra>]'``."""
    module: str
    """The Python package the backend needs."""


BACKENDS: tuple[Backend, ...] = (
    Backend("clip", "image-text features of masked crops, and query embeddings", "OpenCLIP ViT-B/16 laion2b_s34b_b88k",
            "laion/CLIP-ViT-B-16-laion2B-s34B-b88K", "BENCH4D_CLIP", 0.6, 1.0, "captioner", "transformers"),
    Backend("sam", "masks at three levels, associated over time", "SAM ViT-H", "facebook/sam-vit-huge",
            "BENCH4D_SAM", 2.6, 7.0, "captioner", "transformers"),
    Backend("sam-checkpoint", "the same SAM from the official package's checkpoint", "SAM ViT-H (sam_vit_h_4b8939.pth)",
            None, "BENCH4D_SAM_CHECKPOINT", 2.6, 7.0, "sam", "segment_anything"),
    Backend("qwen2-vl", "two-step captions of each object per frame", "Qwen2-VL-7B-Instruct",
            "Qwen/Qwen2-VL-7B-Instruct", "BENCH4D_QWEN2VL", 16.6, 18.0, "captioner", "transformers"),
    Backend("e5-mistral", "caption and query embeddings of the time-varying field", "e5-mistral-7b-instruct",
            None, "BENCH4D_E5_MISTRAL", 14.2, 15.0, "e5mistral", "sentence_transformers"),
)
"""The real track's backends (the oracle track and the bundled text encoders need no weights)."""


def hub_cache() -> Path:
    """The Hugging Face hub cache folder (``$HF_HUB_CACHE``, else ``$HF_HOME/hub``, else ``~/.cache/huggingface/hub``)."""
    if os.environ.get("HF_HUB_CACHE"):
        return Path(os.environ["HF_HUB_CACHE"])
    return Path(os.environ.get("HF_HOME", Path.home() / ".cache" / "huggingface")) / "hub"


@dataclass(frozen=True)
class Located:
    """Where a backend's weights were looked for, and whether they are there."""

    backend: Backend
    path: Optional[Path]
    """The folder or file found (or looked at)."""
    present: bool
    """Whether usable weights are there."""
    source: str
    """How the path was chosen: the environment variable, the hub cache, or nothing."""


WEIGHT_FILES = ("*.safetensors", "*.bin", "*.pth", "*.pt")
"""File patterns that hold weights."""


def _weights_in(path: Path) -> bool:
    """A non-empty weights file, or a folder holding one."""
    if path.is_file():
        return path.stat().st_size > 0
    return path.is_dir() and any(any(path.glob(pattern)) for pattern in WEIGHT_FILES)


def locate(backend: Backend) -> Located:
    """Find ``backend``'s weights: the folder or file its environment variable names, else its hub id's
    newest snapshot in the hub cache."""
    named = os.environ.get(backend.env)
    if named:
        path = Path(named).expanduser()
        return Located(backend, path, _weights_in(path), f"${backend.env}")
    if backend.hub_id is None:
        return Located(backend, None, False, f"set ${backend.env} to the local weights")
    folder = hub_cache() / ("models--" + backend.hub_id.replace("/", "--")) / "snapshots"
    snapshots = sorted(folder.glob("*"), key=lambda p: p.stat().st_mtime) if folder.is_dir() else []
    path = snapshots[-1] if snapshots else folder
    return Located(backend, path, bool(snapshots) and _weights_in(path), "hub cache")


def module_available(name: str) -> bool:
    """Whether the Python package ``name`` can be imported here (without importing it)."""
    import importlib.util

    return importlib.util.find_spec(name) is not None


# ---------------------------------------------------------------------------------------------------
# Memory plans of the large models
# ---------------------------------------------------------------------------------------------------
GIB = 1024 ** 3
WEIGHT_DTYPES = ("float32", "bfloat16", "float16")
"""torch dtype names the vision backends load their weights in."""
WEIGHT_MARGIN = 1.15
"""GPU memory a model takes beyond its half-precision weights (CUDA context, buffers), as a factor."""


@dataclass(frozen=True)
class MemoryPlan:
    """How a large model is loaded on a device: precision, batch size, and whether layers go to the CPU."""

    device: str
    """Where the model runs (``"cpu"``, ``"cuda"``, ``"cuda:1"``)."""
    dtype: Optional[str]
    """torch dtype name of the weights (``None``: the library's default, full precision on the CPU)."""
    batch_size: int
    """Inputs processed at once, from the memory left after the weights."""
    offload: bool
    """Load with ``device_map="auto"``: the layers that do not fit on the GPU stay on the CPU."""
    message: Optional[str] = None
    """One line saying why the model is offloaded (``None``: it fits)."""


def gpu_free_bytes(device: str) -> int:
    """Free memory of CUDA ``device`` in bytes (``torch.cuda.mem_get_info``)."""
    import torch

    return int(torch.cuda.mem_get_info(torch.device(device))[0])


def half_dtype(device: str) -> str:
    """``"bfloat16"`` where the GPU supports it (no overflow in long generations), else ``"float16"``."""
    import torch

    with torch.cuda.device(torch.device(device)):
        return "bfloat16" if torch.cuda.is_bf16_supported() else "float16"


def plan_memory(backend: Backend, device: str, *, per_item_gb: float, max_batch: int = 64,
                free_bytes: Optional[int] = None, dtype: Optional[str] = None, cpu_batch: Optional[int] = None,
                offload: bool = True) -> MemoryPlan:
    """The :class:`MemoryPlan` of ``backend`` on ``device``.

    On the CPU: full precision, ``cpu_batch`` (default ``max_batch``). On CUDA: half precision; the weights
    (``backend.gpu_memory_gb`` x :data:`WEIGHT_MARGIN`) plus one input (``per_item_gb``) must fit in the free
    memory (``free_bytes``, else :func:`gpu_free_bytes`), and the batch is what the rest holds, at most
    ``max_batch``. A model that does not fit is offloaded (``device_map="auto"``, one input at a time) when
    ``offload`` is allowed and ``accelerate`` is installed; otherwise an
    :class:`~benchmark.core.errors.InputError` says what to do.
    """
    from benchmark.core.errors import InputError

    if not str(device).startswith("cuda"):
        return MemoryPlan(device=device, dtype=None, batch_size=max_batch if cpu_batch is None else cpu_batch,
                          offload=False)
    dtype = dtype or half_dtype(device)
    free = gpu_free_bytes(device) if free_bytes is None else int(free_bytes)
    weights = backend.gpu_memory_gb * WEIGHT_MARGIN * GIB
    per_item = max(per_item_gb, 1e-6) * GIB
    if weights + per_item <= free:
        batch = int(max(1, min(max_batch, (free - weights) // per_item)))
        return MemoryPlan(device=device, dtype=dtype, batch_size=batch, offload=False)
    need = f"{backend.model} needs about {(weights + per_item) / GIB:.1f} GB of GPU memory and {free / GIB:.1f} GB is free"
    if not offload:
        raise InputError(None, f"{backend.name} memory",
                         f"{need}: free GPU memory (another process may hold it) or run on the CPU (--device cpu)")
    if not module_available("accelerate"):
        raise InputError(None, f"{backend.name} memory",
                         f"{need}: install accelerate (pip install accelerate) to offload layers to the CPU, or run "
                         "this stage on a larger GPU (captions made elsewhere come in through captions.file)")
    return MemoryPlan(device=device, dtype=dtype, batch_size=1, offload=True,
                      message=f"{need}: loading it with device_map='auto' (layers that do not fit run on the CPU, "
                              "much slower)")


def backend(name: str) -> Backend:
    """The backend called ``name`` in :data:`BACKENDS`."""
    for b in BACKENDS:
        if b.name == name:
            return b
    raise KeyError(name)
