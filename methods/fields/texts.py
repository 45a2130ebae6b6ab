"""Text embeddings a fitted model queries with: each query encoded once, the protocol's canonical phrases
encoded once per protocol."""

from __future__ import annotations

from typing import Optional

import torch

from benchmark.core.protocol import AgnosticQuery

from ..api import Model
from .relevance import encode_canonical


class EncodedQueryModel(Model):
    """A :class:`~methods.api.Model` that answers through the protocol's relevance query. A subclass sets
    ``text_encoder`` and ``device`` in its ``__init__``."""

    text_encoder: object
    device: torch.device
    _canon: Optional[torch.Tensor] = None
    _query_vectors: Optional[dict[str, torch.Tensor]] = None

    def use_protocol(self, protocol) -> None:
        super().use_protocol(protocol)
        self._canon = None  # the canonical phrases are the protocol's

    @property
    def relevance_cfg(self) -> AgnosticQuery:
        """The time-agnostic query rules answered under."""
        return self.protocol.agnostic

    def canonical(self) -> torch.Tensor:
        """[P, D] embeddings of the protocol's canonical phrases (the queries' text encoder)."""
        if self._canon is None:
            self._canon = encode_canonical(self.text_encoder, self.relevance_cfg.canonical_phrases).to(self.device)
        return self._canon

    def query_embedding(self, text: str) -> torch.Tensor:
        """[D] float32 embedding of a query text, encoded once per text."""
        if self._query_vectors is None:
            self._query_vectors = {}
        if text not in self._query_vectors:
            self._query_vectors[text] = torch.as_tensor(self.text_encoder.encode([text], kind="query")[0],
                                                        dtype=torch.float32, device=self.device)
        return self._query_vectors[text]
