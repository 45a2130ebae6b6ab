"""Per-scene feature autoencoder: D-dimensional language features <-> a few latent channels.

The paper compresses CLIP features 512 -> 3 (time-agnostic field) and caption embeddings
4096 -> 6 (time-varying field) so the Gaussians carry only a few channels; queries decode the
rendered latent maps back to D. Loss: MSE + w (1 - cos), Adam, batch 64, 100 epochs (release);
the latent is L2-normalised (release).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..gaussians.optimizer import fast_adam
from .configs import AutoencoderConfig

__all__ = ["AutoencoderConfig", "AutoencoderReport", "FeatureAutoencoder", "train_autoencoder"]


class FeatureAutoencoder(nn.Module):
    """MLP autoencoder ``D -> ... -> latent -> ... -> D``."""

    def __init__(self, input_dim: int, cfg: AutoencoderConfig):
        super().__init__()
        self.input_dim = int(input_dim)
        self.cfg = cfg
        dims = [self.input_dim, *cfg.hidden_dims, cfg.latent_dim]
        enc: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            enc += [nn.Linear(a, b), nn.ReLU()]
        self.encoder = nn.Sequential(*enc[:-1])
        rdims = dims[::-1]
        dec: list[nn.Module] = []
        for a, b in zip(rdims[:-1], rdims[1:]):
            dec += [nn.Linear(a, b), nn.ReLU()]
        self.decoder = nn.Sequential(*dec[:-1])

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """[..., D] -> [..., latent]."""
        z = self.encoder(x)
        return F.normalize(z, dim=-1) if self.cfg.normalize_latent else z

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """[..., latent] -> [..., D] (not normalised; queries normalise)."""
        return self.decoder(z)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(x))


@dataclass
class AutoencoderReport:
    """What training the autoencoder achieved."""

    reconstruction_cosine: float
    """Mean cosine between inputs and their reconstructions (1 = perfect)."""
    steps: int
    seconds: float
    losses: list[float] = field(default_factory=list)


def train_autoencoder(features: np.ndarray | torch.Tensor, cfg: Optional[AutoencoderConfig] = None,
                      *, seed: int = 0, weights: Optional[np.ndarray] = None,
                      device: str | torch.device = "cpu") -> tuple[FeatureAutoencoder, AutoencoderReport]:
    """Fit the autoencoder on ``features`` [M, D] (e.g. one vector per mask), for the epochs of
    :meth:`AutoencoderConfig.for_features` (at least ``min_steps`` steps).

    ``weights`` [M] (e.g. mask areas) sets the sampling probability of each vector, so frequent
    features are reconstructed best; uniform when ``None``.
    """
    x = torch.as_tensor(np.asarray(features, dtype=np.float32), device=device)
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"features must be a non-empty [M, D] array, got shape {tuple(x.shape)}")
    cfg = (cfg or AutoencoderConfig()).for_features(x.shape[0])
    gen = torch.Generator(device="cpu").manual_seed(seed)
    torch.manual_seed(seed)
    model = FeatureAutoencoder(x.shape[1], cfg).to(device)
    opt = fast_adam(model.parameters(), lr=cfg.learning_rate)
    probs = None if weights is None else torch.as_tensor(np.asarray(weights, np.float64) / np.sum(weights))
    steps_per_epoch = max(1, int(np.ceil(x.shape[0] / cfg.batch_size)))
    total = cfg.epochs * steps_per_epoch
    if cfg.max_steps is not None:
        total = min(total, cfg.max_steps)
    # Few distinct vectors: make sure there are enough steps to fit them at all.
    total = max(total, min(cfg.max_steps or 500, 500))
    start = time.perf_counter()
    losses: list[float] = []
    for step in range(total):
        if probs is None:
            idx = torch.randint(0, x.shape[0], (cfg.batch_size,), generator=gen)
        else:
            idx = torch.multinomial(probs, cfg.batch_size, replacement=True, generator=gen)
        batch = x[idx.to(x.device)]
        recon = model(batch)
        loss = F.mse_loss(recon, batch) + cfg.cosine_weight * (
            1.0 - F.cosine_similarity(recon, batch, dim=-1)).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 100 == 0 or step == total - 1:
            losses.append(float(loss.detach()))
    with torch.no_grad():
        cos = F.cosine_similarity(model(x), x, dim=-1).mean().item()
    return model, AutoencoderReport(reconstruction_cosine=cos, steps=total,
                                    seconds=time.perf_counter() - start, losses=losses)
