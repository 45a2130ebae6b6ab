"""The ``clip`` image-text source (real track): CLIP features of masked crops, as LangSplat prepares them.

Per mask (LangSplat / 4D LangSplat release, ``preprocess.py``):

1. zero the image outside the mask;
2. crop the mask's bounding box (inclusive of its last row and column; the release's XYWH box from
   SAM drops them, an off-by-one not copied);
3. pad to a square with zeros, the crop centred (integer offset ``(long - short) // 2``);
4. resize to 224 x 224 (bilinear, as ``cv2.resize``'s default);
5. normalise with CLIP's mean and standard deviation.

:func:`prepare_crops` does this in torch (no torchvision: it breaks the core install), batched.
The encoder is pluggable (:class:`CLIPBackend`):

* :class:`HFCLIPBackend` (default): ``transformers.CLIPModel`` + its tokenizer from a local folder
  or a hub id on the user's machine. The paper's model, OpenCLIP ViT-B-16 laion2b_s34b_b88k, is
  published in this format as ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K`` (:data:`DEFAULT_MODEL`).
* :class:`OpenCLIPBackend` (optional extra ``bench4d[clip]``): ``open_clip`` itself, which imports
  torchvision.

Queries go through the same model's text tower (:class:`CLIPTextEncoder`), so the time-agnostic
query compares text and mask features in one space. No weights can be downloaded here: a missing
model is a clear :class:`~benchmark.core.errors.InputError`.
"""

from __future__ import annotations

import abc
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from ..backends import WEIGHT_DTYPES
from .base import ImageTextEncoder, TextEncoder, TextKind

CLIP_MEAN: tuple[float, float, float] = (0.48145466, 0.4578275, 0.40821073)
"""CLIP's per-channel input mean (OpenAI / OpenCLIP)."""
CLIP_STD: tuple[float, float, float] = (0.26862954, 0.26130258, 0.27577711)
"""CLIP's per-channel input standard deviation."""
CROP_SIZE = 224
"""Side of the square crops (ViT-B-16 input; release: 224)."""
DEFAULT_MODEL = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
"""Hub id of OpenCLIP ViT-B-16 laion2b_s34b_b88k in transformers format (loaded on a user's machine)."""
OPENCLIP_ARCH = "ViT-B-16"
OPENCLIP_PRETRAINED = "laion2b_s34b_b88k"
CLIP_GB_PER_CROP = 0.01
"""GPU memory of one crop through the image tower in half precision, GB: its input and one layer's attention
and MLP activations at a time, with margin (an estimate)."""
CLIP_CPU_BATCH = 32
"""Crops encoded at once on the CPU."""
CLIP_MAX_BATCH = 512
"""Most crops encoded at once on CUDA (a frame rarely has more masks over its three levels)."""


def mask_boxes(masks: torch.Tensor) -> torch.Tensor:
    """[M, H, W] bool -> [M, 4] int64 inclusive boxes ``(y0, y1, x0, x1)``; an empty mask gives the whole image."""
    m, h, w = masks.shape
    rows = masks.any(2)  # [M, H]
    cols = masks.any(1)  # [M, W]
    ar_h = torch.arange(h, device=masks.device)
    ar_w = torch.arange(w, device=masks.device)
    big = torch.tensor(10 ** 9, device=masks.device)
    y0 = torch.where(rows, ar_h, big).amin(1)
    y1 = torch.where(rows, ar_h, -big).amax(1)
    x0 = torch.where(cols, ar_w, big).amin(1)
    x1 = torch.where(cols, ar_w, -big).amax(1)
    empty = ~rows.any(1)
    y0 = torch.where(empty, torch.zeros_like(y0), y0)
    y1 = torch.where(empty, torch.full_like(y1, h - 1), y1)
    x0 = torch.where(empty, torch.zeros_like(x0), x0)
    x1 = torch.where(empty, torch.full_like(x1, w - 1), x1)
    return torch.stack([y0, y1, x0, x1], 1)


def prepare_crops(image: torch.Tensor, masks: torch.Tensor, *, size: int = CROP_SIZE,
                  mean: Sequence[float] = CLIP_MEAN, std: Sequence[float] = CLIP_STD) -> torch.Tensor:
    """Masked, box-cropped, square-padded, resized and normalised crops (module docstring).

    Args:
        image: [H, W, 3] float RGB in [0, 1].
        masks: [M, H, W] bool.
    Returns:
        [M, 3, size, size] float32 network input.
    """
    image = image.float()
    boxes = mask_boxes(masks).tolist()
    mean_t = torch.tensor(mean, dtype=torch.float32, device=image.device).view(3, 1, 1)
    std_t = torch.tensor(std, dtype=torch.float32, device=image.device).view(3, 1, 1)
    out = image.new_empty(masks.shape[0], 3, size, size)
    for k, (y0, y1, x0, x1) in enumerate(boxes):
        crop = (image[y0:y1 + 1, x0:x1 + 1] * masks[k, y0:y1 + 1, x0:x1 + 1, None]).permute(2, 0, 1)  # [3, h, w]
        h, w = crop.shape[1:]
        side = max(h, w)
        square = crop.new_zeros(3, side, side)
        oy, ox = (side - h) // 2, (side - w) // 2
        square[:, oy:oy + h, ox:ox + w] = crop
        resized = F.interpolate(square[None], size=(size, size), mode="bilinear", align_corners=False)[0]
        out[k] = (resized - mean_t) / std_t
    return out


# ---------------------------------------------------------------------------------------------------
# Backends
# ---------------------------------------------------------------------------------------------------
class CLIPBackend(abc.ABC):
    """A CLIP model: images and texts into one embedding space."""

    image_size: int = CROP_SIZE
    mean: tuple[float, float, float] = CLIP_MEAN
    std: tuple[float, float, float] = CLIP_STD

    @abc.abstractmethod
    def encode_images(self, pixels: torch.Tensor) -> torch.Tensor:
        """[B, 3, S, S] normalised input -> [B, D] embeddings (not necessarily normalised)."""

    @abc.abstractmethod
    def encode_texts(self, texts: list[str]) -> torch.Tensor:
        """Texts -> [n, D] embeddings (not necessarily normalised)."""

    @abc.abstractmethod
    def config(self) -> dict[str, Any]:
        """What identifies the model (goes into cache keys)."""


def _pooled(out: Any) -> torch.Tensor:
    """``get_*_features`` returns a tensor (transformers 4) or an output with ``pooler_output`` (5)."""
    return out if torch.is_tensor(out) else out.pooler_output


class HFCLIPBackend(CLIPBackend):
    """``transformers.CLIPModel`` and its tokenizer from ``model`` (a local folder or a hub id)."""

    def __init__(self, model: str | Path = DEFAULT_MODEL, *, device: str = "cpu", dtype: str = "float32",
                 local_files_only: bool = True) -> None:
        try:
            from transformers import AutoTokenizer, CLIPModel
        except ImportError as err:  # pragma: no cover - transformers is a declared extra
            raise InputError(None, "clip", "package 'transformers' is not installed (pip install 'bench4d[captioner]')") from err
        if dtype not in WEIGHT_DTYPES:
            raise InputError(None, "clip dtype", f"unknown dtype {dtype!r}; use one of {', '.join(WEIGHT_DTYPES)}")
        self.model_name = str(model)
        self.device = torch.device(device)
        self.dtype = getattr(torch, dtype)
        try:
            self.model = CLIPModel.from_pretrained(self.model_name, local_files_only=local_files_only,
                                                   torch_dtype=self.dtype).to(self.device).eval()
            self.tokenizer = AutoTokenizer.from_pretrained(self.model_name, local_files_only=local_files_only)
        except (OSError, ValueError) as err:
            raise InputError(Path(self.model_name) if Path(self.model_name).exists() else None, "clip model",
                             f"cannot load CLIP weights from {self.model_name!r} ({err.__class__.__name__}: "
                             f"{str(err).splitlines()[0] if str(err) else ''}); pass model=<local folder of a "
                             f"transformers CLIP model> (default hub id {DEFAULT_MODEL!r}, fetched on your machine "
                             "with local_files_only=False)") from None
        vision = self.model.config.vision_config
        self.image_size = int(vision.image_size)
        self.max_length = int(getattr(self.model.config.text_config, "max_position_embeddings", 77))

    @torch.no_grad()
    def encode_images(self, pixels: torch.Tensor) -> torch.Tensor:
        out = self.model.get_image_features(pixel_values=pixels.to(self.device, self.dtype))
        return _pooled(out).float()

    @torch.no_grad()
    def encode_texts(self, texts: list[str]) -> torch.Tensor:
        tok = self.tokenizer(texts, padding=True, truncation=True, max_length=self.max_length, return_tensors="pt")
        out = self.model.get_text_features(input_ids=tok["input_ids"].to(self.device),
                                           attention_mask=tok["attention_mask"].to(self.device))
        return _pooled(out).float()

    def config(self) -> dict[str, Any]:
        return {"backend": "transformers", "model": Path(self.model_name).name or self.model_name,
                "dtype": str(self.dtype).replace("torch.", ""), "image_size": self.image_size}


class OpenCLIPBackend(CLIPBackend):
    """``open_clip`` (optional: ``pip install 'bench4d[clip]'``, which brings torchvision)."""

    def __init__(self, arch: str = OPENCLIP_ARCH, pretrained: str = OPENCLIP_PRETRAINED, *, device: str = "cpu",
                 precision: str = "fp32") -> None:
        try:
            import open_clip
        except Exception as err:  # ImportError, or torchvision failing to import inside open_clip
            raise InputError(None, "clip backend open_clip",
                             f"cannot import open_clip ({err.__class__.__name__}: {err}); install the optional "
                             "extra with 'pip install bench4d[clip]' (it needs torchvision) or use backend='hf'") from None
        self.arch, self.pretrained = arch, pretrained
        self.device = torch.device(device)
        try:
            model, _, _ = open_clip.create_model_and_transforms(arch, pretrained=pretrained, precision=precision)
        except Exception as err:
            raise InputError(None, "clip model", f"open_clip cannot load {arch}/{pretrained}: {err}") from None
        self.model = model.to(self.device).eval()
        self.tokenizer = open_clip.get_tokenizer(arch)
        size = getattr(self.model.visual, "image_size", CROP_SIZE)
        self.image_size = int(size[0] if isinstance(size, (tuple, list)) else size)

    @torch.no_grad()
    def encode_images(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.model.encode_image(pixels.to(self.device)).float()

    @torch.no_grad()
    def encode_texts(self, texts: list[str]) -> torch.Tensor:
        return self.model.encode_text(self.tokenizer(texts).to(self.device)).float()

    def config(self) -> dict[str, Any]:
        return {"backend": "open_clip", "arch": self.arch, "pretrained": self.pretrained}


# ---------------------------------------------------------------------------------------------------
# Sources
# ---------------------------------------------------------------------------------------------------
class CLIPTextEncoder(TextEncoder):
    """CLIP's text tower as a :class:`TextEncoder` (symmetric: query and passage are encoded alike)."""

    name = "clip-text"

    def __init__(self, backend: CLIPBackend) -> None:
        super().__init__()
        self.backend = backend
        self._dim: Optional[int] = None

    @property
    def dim(self) -> int:
        if self._dim is None:
            self._dim = int(self.encode(["object"]).shape[1])
        return self._dim

    def _encode(self, texts: list[str], kind: TextKind) -> np.ndarray:
        return self.backend.encode_texts(texts).cpu().numpy()

    def config(self) -> dict[str, Any]:
        return {"name": self.name, **self.backend.config()}


class CLIPImageTextEncoder(ImageTextEncoder):
    """One CLIP feature per mask from its prepared crop (module docstring)."""

    name = "clip"
    track = "real"

    def __init__(self, backend: CLIPBackend, *, batch_size: int = 32) -> None:
        self.backend = backend
        self.batch_size = int(batch_size)
        self._text = CLIPTextEncoder(backend)

    @property
    def text_encoder(self) -> TextEncoder:
        return self._text

    def config(self) -> dict[str, Any]:
        return {"name": self.name, **self.backend.config(), "crop": "mask-zeroed box, square pad, bilinear",
                "crop_size": self.backend.image_size, "mean": list(self.backend.mean), "std": list(self.backend.std)}

    @torch.no_grad()
    def encode_masks(self, image: np.ndarray, masks: np.ndarray, *, frame: Frame,
                     levels: Optional[np.ndarray] = None) -> np.ndarray:
        """(M, D) float32 unit rows for (M, H, W) ``masks`` of the (H, W, 3) ``image``."""
        masks = np.asarray(masks, dtype=bool)
        if masks.ndim != 3 or masks.shape[1:] != image.shape[:2]:
            raise InputError(frame.image_path, "masks", f"expected (M, {image.shape[0]}, {image.shape[1]}), got {masks.shape}")
        img = torch.as_tensor(np.asarray(image, dtype=np.float32))
        feats = []
        for s in range(0, masks.shape[0], self.batch_size):
            crops = prepare_crops(img, torch.as_tensor(masks[s:s + self.batch_size]), size=self.backend.image_size,
                                  mean=self.backend.mean, std=self.backend.std)
            feats.append(F.normalize(self.backend.encode_images(crops), dim=-1).cpu())
        if not feats:
            return np.zeros((0, self._text.dim), dtype=np.float32)
        return torch.cat(feats).numpy().astype(np.float32)


class HFCLIPImageTextEncoder(CLIPImageTextEncoder):
    """:class:`CLIPImageTextEncoder` on ``transformers.CLIPModel`` (:class:`HFCLIPBackend`)."""

    def __init__(self, model: str | Path = DEFAULT_MODEL, *, device: str = "cpu", batch_size: int = 32,
                 dtype: str = "float32", local_files_only: bool = True) -> None:
        super().__init__(HFCLIPBackend(model, device=device, dtype=dtype, local_files_only=local_files_only),
                         batch_size=batch_size)


def plan_clip(device: str, *, free_bytes: Optional[int] = None, dtype: Optional[str] = None):
    """The :class:`~methods.backends.MemoryPlan` of the CLIP image tower on ``device``: on the CPU full
    precision and :data:`CLIP_CPU_BATCH` crops at once; on CUDA half precision (``dtype`` overrides it) and
    the crops the free memory (``free_bytes``, else what the GPU reports) holds beside the weights, at most
    :data:`CLIP_MAX_BATCH`. A GPU without room for the weights is a one-line
    :class:`~benchmark.core.errors.InputError` (the model is small: no offloading)."""
    from methods.backends import backend, plan_memory

    return plan_memory(backend("clip"), device, per_item_gb=CLIP_GB_PER_CROP, max_batch=CLIP_MAX_BATCH,
                       cpu_batch=CLIP_CPU_BATCH, free_bytes=free_bytes, dtype=dtype, offload=False)


def create(scene: Scene, *, text_encoder: TextEncoder = None, device: str = "cpu", backend: str = "hf",
           model: Optional[str] = None, batch_size: Optional[int] = None, dtype: Optional[str] = None,
           free_bytes: Optional[int] = None, **options: Any) -> CLIPImageTextEncoder:
    """Factory of the registry.

    ``backend="hf"`` (default): ``model`` = local folder or hub id (default :data:`DEFAULT_MODEL`; the
    environment variable ``BENCH4D_CLIP`` overrides it), ``local_files_only`` (default True).
    ``backend="open_clip"``: ``arch``, ``pretrained``, ``precision``. ``batch_size`` and ``dtype`` (hf)
    default to the memory plan (:func:`plan_clip`; ``free_bytes``: free GPU memory to plan with). The run's
    ``text_encoder`` is not used: queries must go through CLIP's own text tower.
    """
    import os

    plan = plan_clip(device, free_bytes=free_bytes, dtype=dtype)
    batch = int(batch_size) if batch_size is not None else plan.batch_size
    if backend == "hf":
        return HFCLIPImageTextEncoder(model or os.environ.get("BENCH4D_CLIP", DEFAULT_MODEL), device=device,
                                      batch_size=batch, dtype=dtype or plan.dtype or "float32", **options)
    if backend == "open_clip":
        return CLIPImageTextEncoder(OpenCLIPBackend(device=device, **options), batch_size=batch)
    raise InputError(None, "clip backend", f"unknown backend {backend!r}; use 'hf' or 'open_clip'")
