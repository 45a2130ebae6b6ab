"""The time-agnostic query of 4D LangSplat / LangSplat, exactly as ``shared/docs/protocol.md``.

Given decoded per-pixel language features of the three SAM levels, a query embedding and the
canonical phrases' embeddings:

1. L2-normalise each pixel's feature.
2. LERF relevance: ``r = min_c exp(s q.f) / (exp(s q.f) + exp(s c.f))`` with ``s = 10``;
   equivalently ``sigmoid(s (q.f - max_c c.f))`` (computed that way: no overflow).
3. Smooth: ``v = (v + avgpool_k(v)) / 2`` with a ``k x k`` (29 at the paper's 960x536; scaled to the
   rendered resolution by default, see :attr:`benchmark.core.protocol.AgnosticQuery.kernel_scaling`) window, stride 1, and
   the padding excluded from the mean.
4. Rescale by min-max and threshold (release, the default: ``clip(2 (v - min) / (max - min) - 1, 0, 1) > 0.4``,
   i.e. rescaled > 0.7; the paper's wording: rescaled > 0.4).
5. Majority filter ``7 x 7`` (mean of the binary mask > 0.5).
6. Level choice: the level whose smoothed relevance map has the highest maximum.

All functions take torch tensors and run on CPU or CUDA; every constant is a field of
:class:`benchmark.core.protocol.AgnosticQuery`, the time-agnostic part of the evaluation protocol.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from benchmark.core.protocol import CANONICAL_PHRASES, AgnosticQuery

def relevance(features: torch.Tensor, query: torch.Tensor, canon: torch.Tensor,
              temperature: float = 10.0) -> torch.Tensor:
    """LERF relevance of every pixel.

    Args:
        features: [..., D] decoded language features (normalised here).
        query:    [D] query text embedding (normalised here).
        canon:    [P, D] canonical phrase embeddings (normalised here).
    Returns:
        [...] relevance in (0, 1).
    """
    f = F.normalize(features, dim=-1)
    q = F.normalize(query, dim=-1)
    c = F.normalize(canon, dim=-1)
    sim_q = f @ q  # [...]
    sim_c = (f @ c.T).amax(dim=-1)  # [...]: the min over phrases is attained at the max c.f
    return torch.sigmoid(temperature * (sim_q - sim_c))


def smooth(relevance_map: torch.Tensor, kernel: int) -> torch.Tensor:
    """``(v + avgpool_k(v)) / 2`` with padding excluded from the mean.

    Args:
        relevance_map: [L, H, W] or [H, W].
    """
    squeeze = relevance_map.dim() == 2
    v = relevance_map[None] if squeeze else relevance_map
    pooled = F.avg_pool2d(v[:, None], kernel, stride=1, padding=kernel // 2,
                          count_include_pad=False)[:, 0]
    out = 0.5 * (v + pooled)
    return out[0] if squeeze else out


def rescaled(values: torch.Tensor) -> torch.Tensor:
    """Min-max rescale each map of [L, H, W] (or [H, W]) to [0, 1]; a constant map becomes 0."""
    flat = values.flatten(-2)
    lo = flat.amin(-1)[..., None, None]
    hi = flat.amax(-1)[..., None, None]
    return (values - lo) / (hi - lo).clamp_min(1e-12)


def threshold_mask(smoothed: torch.Tensor, cfg: AgnosticQuery) -> torch.Tensor:
    """Binary mask from a smoothed relevance map (step 4 of the protocol)."""
    x = rescaled(smoothed)
    if cfg.threshold_rule == "stretched":
        x = (2.0 * x - 1.0).clamp(0.0, 1.0)
    return x > cfg.threshold


def majority_filter(mask: torch.Tensor, kernel: int, fraction: float = 0.5) -> torch.Tensor:
    """Keep a pixel where more than ``fraction`` of its ``kernel x kernel`` window is set.

    The window mean excludes padding, so borders are judged on the pixels that exist.
    Args:
        mask: [..., H, W] bool.
    """
    shape = mask.shape
    m = mask.reshape(-1, 1, *shape[-2:]).float()
    mean = F.avg_pool2d(m, kernel, stride=1, padding=kernel // 2, count_include_pad=False)
    return (mean[:, 0] > fraction).reshape(shape)


@dataclass
class AgnosticResult:
    """Answer of the time-agnostic query on one frame."""

    mask: torch.Tensor
    """[H, W] bool final mask (after the majority filter)."""
    mask_unfiltered: torch.Tensor
    """[H, W] bool mask before the majority filter (the release's time-sensitive query uses it)."""
    relevance: torch.Tensor
    """[H, W] smoothed relevance of the chosen level."""
    level: int
    """Index of the chosen level (0 small / 1 middle / 2 large)."""
    level_peaks: torch.Tensor
    """[L] maximum smoothed relevance of each level."""


def query_levels(level_features: torch.Tensor, query: torch.Tensor, canon: torch.Tensor,
                 cfg: Optional[AgnosticQuery] = None) -> AgnosticResult:
    """Run steps 2-6 on decoded features of every level of one frame.

    Args:
        level_features: [L, H, W, D] decoded features (L = 3 SAM levels).
        query:          [D] query embedding.
        canon:          [P, D] canonical phrase embeddings.
    """
    cfg = cfg or AgnosticQuery()
    rel = relevance(level_features, query, canon, cfg.temperature)  # [L, H, W]
    return answer_from_relevance(rel, cfg)


def answer_from_relevance(rel: torch.Tensor, cfg: AgnosticQuery) -> AgnosticResult:
    """Steps 3-6 (smoothing, level choice, threshold, majority filter) on per-level relevance.

    Args:
        rel: [L, H, W] relevance of each level (step 2).
    """
    smoothing_kernel, majority_kernel = cfg.kernels_for(*rel.shape[-2:])
    sm = smooth(rel, smoothing_kernel)
    peaks = sm.flatten(1).amax(1)
    level = int(torch.argmax(peaks))
    raw_mask = threshold_mask(sm[level], cfg)
    mask = majority_filter(raw_mask, majority_kernel, cfg.majority_fraction)
    return AgnosticResult(mask=mask, mask_unfiltered=raw_mask, relevance=sm[level], level=level,
                          level_peaks=peaks)


def spatial_mask(result: AgnosticResult, rules) -> torch.Tensor:
    """[H, W] bool: the time-sensitive query's spatial mask on a frame, before or after the majority
    filter as :attr:`benchmark.core.protocol.SensitiveQuery.mask` says."""
    return result.mask_unfiltered if rules.mask == "unfiltered" else result.mask


def encode_canonical(text_encoder, phrases: Sequence[str] = CANONICAL_PHRASES) -> torch.Tensor:
    """[P, D] embeddings of the canonical phrases with any encoder exposing ``encode(texts)``."""
    emb = text_encoder.encode(list(phrases))
    return torch.as_tensor(emb, dtype=torch.float32)
