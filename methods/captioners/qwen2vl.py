"""The ``qwen2-vl`` captioner: Qwen2-VL (transformers) with 4D LangSplat's two-step prompting.

Step 1 shows the MLLM frames of the object's video (visually prompted: red outline, grey blurred
background) and asks what the outlined object is and how it changes; step 2 shows one frame (or the
frame between two neighbouring ones, text prompt ``video+image``) with that description as context
and asks for the object's state in that frame only.

Prompts. The wording below is ours: it follows the structure and instructions of the prompts in the
public 4D LangSplat release (``preprocess/generate_video_captions.py``: identify the red-outlined
object and summarise its transformation; then, given that summary, describe only the state visible in
the given image, with examples of what not to carry over from the context), without copying their
text. To reproduce the release exactly, put its prompts in a JSON file ``{"video": ...,
"frame_with_context": ... "{description}" ..., "frame_alone": ...}`` and pass ``prompts_file=``.

Inputs are assembled here (Qwen2-VL's chat format, image placeholders expanded to the number of
vision tokens) with the tokenizer and the PIL image processor, so neither torchvision nor
``qwen_vl_utils`` is needed. The video of step 1 is given as a sequence of images (the release feeds
an mp4 through ``qwen_vl_utils``; Qwen2-VL reads both).

Weights: ``model=`` a local folder or a hub id (``$BENCH4D_QWEN2VL`` by default, else
``Qwen/Qwen2-VL-7B-Instruct``, which transformers fetches only where the hub is reachable).
:func:`tiny_random_components` builds a tiny randomly initialised model offline: it exercises the
whole flow (shapes, prompts, caching) and produces noise, never captions to report.
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import Captioner

DEFAULT_MODEL = "Qwen/Qwen2-VL-7B-Instruct"
"""The paper's captioner."""
MODEL_ENV = "BENCH4D_QWEN2VL"
"""Environment variable naming the default model folder or hub id."""


@dataclass(frozen=True)
class QwenPrompts:
    """The texts of the two steps (see the module docstring for where they come from)."""

    system: str = "You are a helpful assistant."
    """System message (Qwen2-VL's chat template default)."""
    video: str = ("The object to describe is outlined in red in these frames of a video; everything else is "
                  "greyed out and blurred. First say what the red-outlined object is. Then summarise briefly "
                  "how this object changes over the video.")
    """Step 1: identify the outlined object and summarise how it changes."""
    frame_with_context: str = (
        "Context: over the whole video the object changes as follows: '{description}'. "
        "{images} Describe the state of the red-outlined object in {target} only, not the process of the "
        "whole video. State only what can be seen in {target}; do not repeat the context. For example, if "
        "the context says the object goes up and down but here it is going down, say only that it is going "
        "down; if the context says it breaks but here it is still whole, say that it is whole and intact; if "
        "the context says it turns from green to blue and here it is blue, say that it is blue.")
    """Step 2 with the video-level description (``{description}``, ``{images}``, ``{target}`` are filled in)."""
    frame_alone: str = "{images} Describe the current state of the red-outlined object in {target} in one sentence."
    """Step 2 without context (text prompt ``none``)."""

    @staticmethod
    def from_file(path: str | Path) -> "QwenPrompts":
        """Prompts from a JSON object with some of the keys ``system``, ``video``,
        ``frame_with_context``, ``frame_alone`` (others keep their defaults)."""
        doc = read_json(path)
        if not isinstance(doc, dict):
            raise InputError(path, None, "prompts file must be a JSON object")
        known = set(QwenPrompts.__dataclass_fields__)
        unknown = sorted(set(doc) - known)
        if unknown:
            raise InputError(path, unknown[0], f"unknown prompt; known: {', '.join(sorted(known))}")
        for key, value in doc.items():
            if not isinstance(value, str):
                raise InputError(path, key, "must be a string")
        if "frame_with_context" in doc and "{description}" not in doc["frame_with_context"]:
            raise InputError(path, "frame_with_context", "must contain the placeholder {description}")
        return QwenPrompts(**doc)


def _image_words(count: int) -> tuple[str, str]:
    """(sentence introducing the pictures, how to name the one to describe)."""
    if count == 1:
        return "", "this picture"
    if count == 3:
        return ("Pictures 1 and 3 are the neighbouring frames, given as context; Picture 2 is the frame "
                "to describe."), "Picture 2"
    return f"Pictures 1 to {count} are frames of the video.", f"Picture {count // 2 + 1}"


def tiny_random_components(seed: int = 0):
    """(model, tokenizer, image processor) of a tiny randomly initialised Qwen2-VL, built offline.

    For tests and smoke runs of the flow only: what it generates is noise.
    """
    import torch
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, Qwen2VLConfig, Qwen2VLForConditionalGeneration
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    special = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
               "<|image_pad|>", "<|video_pad|>"]
    words = ("a the object is open closed whole broken red cup box bar state in this picture video frame "
             "moving up down dark light full empty").split()
    vocab = {w: i for i, w in enumerate(["[UNK]", *special, *words])}
    backend = Tokenizer(models.WordLevel(vocab=vocab, unk_token="[UNK]"))
    backend.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=backend, unk_token="[UNK]", eos_token="<|im_end|>",
                                        pad_token="<|endoftext|>", additional_special_tokens=special)
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in special}
    config = Qwen2VLConfig(
        text_config=dict(vocab_size=len(tokenizer), hidden_size=32, intermediate_size=64, num_hidden_layers=1,
                         num_attention_heads=2, num_key_value_heads=1, max_position_embeddings=4096,
                         rope_scaling={"type": "mrope", "mrope_section": [2, 3, 3]},
                         bos_token_id=ids["<|endoftext|>"], eos_token_id=ids["<|im_end|>"],
                         pad_token_id=ids["<|endoftext|>"]),
        vision_config=dict(depth=1, embed_dim=32, hidden_size=32, num_heads=2, mlp_ratio=2, patch_size=14,
                           spatial_merge_size=2, in_chans=3, temporal_patch_size=2),
        image_token_id=ids["<|image_pad|>"], video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"], vision_end_token_id=ids["<|vision_end|>"],
        bos_token_id=ids["<|endoftext|>"], eos_token_id=ids["<|im_end|>"], pad_token_id=ids["<|endoftext|>"])
    torch.manual_seed(seed)
    model = Qwen2VLForConditionalGeneration(config).eval()
    processor = Qwen2VLImageProcessorPil(min_pixels=56 * 56, max_pixels=112 * 112)
    return model, tokenizer, processor


QWEN_TOKENS_PER_REQUEST_GB = 2.0
"""GPU memory of one request (activations and KV cache of a few frames' vision tokens plus the answer)."""


def load_components(model: str, *, device: str = "cpu", dtype: str = "auto", max_pixels: Optional[int] = None,
                    free_bytes: Optional[int] = None):
    """(model, tokenizer, image processor) of a Qwen2-VL checkpoint (folder or hub id).

    On CUDA the model loads by its :func:`methods.backends.plan_memory` plan: half precision (``dtype="auto"``),
    and with ``device_map="auto"`` (CPU offload, one line on stderr saying so) where it does not fit in the
    free memory (``free_bytes``, else what the GPU reports)."""
    try:
        import torch
        from transformers import AutoTokenizer, Qwen2VLForConditionalGeneration
        from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil
    except ImportError as err:
        raise InputError(None, "captioner qwen2-vl", f"transformers with Qwen2-VL is needed ({err})") from None
    from methods.backends import backend, plan_memory

    plan = plan_memory(backend("qwen2-vl"), device, per_item_gb=QWEN_TOKENS_PER_REQUEST_GB, max_batch=1,
                       free_bytes=free_bytes, dtype=None if dtype == "auto" else dtype)
    if plan.message:
        print(f"qwen2-vl: {plan.message}", file=sys.stderr)
    name = plan.dtype or dtype
    kwargs: dict[str, Any] = {"torch_dtype": name if name == "auto" else getattr(torch, name)}
    if plan.offload:
        kwargs["device_map"] = "auto"
    try:
        net = Qwen2VLForConditionalGeneration.from_pretrained(model, **kwargs)
        net = (net if plan.offload else net.to(device)).eval()
        tokenizer = AutoTokenizer.from_pretrained(model)
        extra = {} if max_pixels is None else {"max_pixels": int(max_pixels)}
        processor = Qwen2VLImageProcessorPil.from_pretrained(model, **extra)
    except (OSError, ValueError) as err:
        raise InputError(Path(model) if Path(model).exists() else None, "captioner qwen2-vl model",
                         f"cannot load Qwen2-VL from {model!r}: {err}. Pass model=<local folder of "
                         f"Qwen2-VL-7B-Instruct> or set ${MODEL_ENV}") from None
    return net, tokenizer, processor


class Qwen2VLCaptioner(Captioner):
    """Qwen2-VL, two-step prompting (module docstring); greedy decoding (deterministic)."""

    name = "qwen2-vl"
    track = "real"
    uses_images = True

    def __init__(self, scene: Optional[Scene] = None, *, model: Optional[str] = None, device: str = "cpu",
                 dtype: str = "auto", max_new_tokens: int = 128, max_pixels: Optional[int] = None,
                 prompts_file: Optional[str] = None, components: Optional[tuple] = None,
                 label: Optional[str] = None) -> None:
        """
        Args:
            model: folder or hub id (default ``$BENCH4D_QWEN2VL`` or :data:`DEFAULT_MODEL`).
            max_new_tokens: generation length of each answer (release: 128).
            max_pixels: cap on the pixels of each image fed to the vision tower (processor default if None).
            prompts_file: JSON prompts replacing the defaults (:meth:`QwenPrompts.from_file`).
            components: ``(model, tokenizer, image processor)`` already built (tests:
                :func:`tiny_random_components`); ``label`` then names them in cache keys.
        """
        self.model_id = model or os.environ.get(MODEL_ENV) or DEFAULT_MODEL
        self.prompts = QwenPrompts.from_file(prompts_file) if prompts_file else QwenPrompts()
        self.max_new_tokens = int(max_new_tokens)
        self.device = device
        if components is not None:
            self.net, self.tokenizer, self.processor = components
            self.model_id = label or "custom"
        else:
            self.net, self.tokenizer, self.processor = load_components(self.model_id, device=device, dtype=dtype,
                                                                       max_pixels=max_pixels)
        self.history: list[dict[str, Any]] = []
        """Every request made: ``{"step", "images", "prompt", "answer", "image_grid_thw"}`` (for tests and logs)."""

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "model": Path(self.model_id).name if os.sep in self.model_id else self.model_id,
                "max_new_tokens": self.max_new_tokens, "prompts": asdict(self.prompts),
                "max_pixels": getattr(self.processor, "max_pixels", None)}

    # -- one request -------------------------------------------------------------------------------
    def chat_text(self, num_images: int, text: str) -> str:
        """The prompt in Qwen2-VL's chat format with one placeholder per image (expanded later)."""
        vision = "".join(f"Picture {k + 1}: <|vision_start|><|image_pad|><|vision_end|>" if num_images > 1
                         else "<|vision_start|><|image_pad|><|vision_end|>" for k in range(num_images))
        return (f"<|im_start|>system\n{self.prompts.system}<|im_end|>\n"
                f"<|im_start|>user\n{vision}{text}<|im_end|>\n<|im_start|>assistant\n")

    def generate(self, images: Sequence[np.ndarray], text: str, step: str) -> str:
        """Answer ``text`` about ``images`` ((H, W, 3) float RGB in [0, 1]) with greedy decoding."""
        import torch
        from PIL import Image

        pil = [Image.fromarray(np.clip(np.asarray(im) * 255.0 + 0.5, 0, 255).astype(np.uint8)) for im in images]
        chat = self.chat_text(len(pil), text)
        kwargs: dict[str, Any] = {}
        grid = None
        if pil:
            vis = self.processor(images=pil, return_tensors="pt")
            grid = vis["image_grid_thw"]
            merge = int(self.processor.merge_size) ** 2
            counts = [int(g.prod()) // merge for g in grid]
            pieces = chat.split("<|image_pad|>")
            chat = pieces[0] + "".join("<|image_pad|>" * n + rest for n, rest in zip(counts, pieces[1:]))
            kwargs = {"pixel_values": vis["pixel_values"].to(self.device, dtype=self.net.dtype),
                      "image_grid_thw": grid.to(self.device)}
        enc = self.tokenizer(chat, return_tensors="pt", add_special_tokens=False)
        with torch.no_grad():
            out = self.net.generate(input_ids=enc["input_ids"].to(self.device),
                                    attention_mask=enc["attention_mask"].to(self.device),
                                    max_new_tokens=self.max_new_tokens, do_sample=False, **kwargs)
        answer = self.tokenizer.decode(out[0, enc["input_ids"].shape[1]:], skip_special_tokens=True).strip()
        self.history.append({"step": step, "images": len(pil), "prompt": text, "answer": answer,
                             "image_grid_thw": None if grid is None else grid.tolist(),
                             "input_tokens": int(enc["input_ids"].shape[1])})
        return answer

    # -- the two steps -----------------------------------------------------------------------------
    def describe_video(self, obj: int, frames: Sequence[Frame], images: Sequence[np.ndarray]) -> str:
        if not images:
            raise ValueError("the video-level description needs the object's frames")
        return self.generate(images, self.prompts.video, "video")

    def caption_frame(self, obj: int, frame: Frame, images: Sequence[np.ndarray], *,
                      description: Optional[str]) -> str:
        if not images:
            raise ValueError("a frame caption needs the frame's image")
        intro, target = _image_words(len(images))
        if description is None:
            text = self.prompts.frame_alone.format(images=intro, target=target).strip()
        else:
            text = self.prompts.frame_with_context.format(description=description, images=intro,
                                                          target=target).strip()
        return self.generate(images, " ".join(text.split()), "frame")
