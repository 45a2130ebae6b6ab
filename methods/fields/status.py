"""Time-varying semantic fields: the status deformable network and the Non-Status baseline.

Status deformable network (4D LangSplat): each Gaussian carries ``K`` state vectors in the caption
latent space; a small MLP on the (frozen) 4D-GS HexPlane feature at ``(x, t)`` gives ``K`` weights and
the Gaussian's feature at time ``t`` is the weighted sum of its states. The paper says the weights
sum to one (softmax, our default); the release has no softmax (``weight_mode="linear"``).

Model no more than a scene needs: Gaussians whose semantics never change (``semantic_dynamic`` is
False) carry ONE vector, not ``K`` states, and skip the MLP.

Non-Status Field (baseline): ``f(x, t) = f_static + MLP(hexplane(x, t))``, a direct deformation of
the feature instead of a mixture of states.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn

from .configs import StatusFieldConfig

__all__ = ["StatusFieldConfig", "StatusField", "NonStatusField", "RowPlan"]


class RowPlan:
    """Where a view's Gaussians (``rows``: the ones its supervised pixels blend, ascending) sit in a field's
    parameters, so a training step evaluates those rows only: a Gaussian no supervised pixel sees gets a
    zero gradient either way, so the step is the same up to float rounding of the network's sums.

    ``hexplane_index``: the rows of the module's HexPlane input to feed (None: the module takes none);
    ``dynamic_at`` / ``static_at``: positions within ``rows`` of the Gaussians with states / one vector;
    ``static_index``: those one-vector Gaussians' positions in the module's ``fixed`` parameter."""

    def __init__(self, rows: torch.Tensor, hexplane_index: Optional[torch.Tensor] = None,
                 dynamic_at: Optional[torch.Tensor] = None, static_at: Optional[torch.Tensor] = None,
                 static_index: Optional[torch.Tensor] = None) -> None:
        self.rows, self.hexplane_index = rows, hexplane_index
        self.dynamic_at, self.static_at, self.static_index = dynamic_at, static_at, static_index


class StatusField(nn.Module):
    """Per-Gaussian states mixed by weights predicted from the HexPlane feature at (x, t)."""

    def __init__(self, static_features: torch.Tensor, hexplane_dim: int,
                 semantic_dynamic: Optional[torch.Tensor] = None,
                 cfg: Optional[StatusFieldConfig] = None, seed: int = 0):
        """
        Args:
            static_features:  [N, D] initial (time-averaged) latent feature of every Gaussian.
            hexplane_dim:     F, dimension of the HexPlane feature fed to the weight MLP.
            semantic_dynamic: [N] bool, Gaussians whose semantics change over time (all if None).
        """
        super().__init__()
        cfg = cfg or StatusFieldConfig()
        self.cfg = cfg
        n, d = static_features.shape
        dyn = torch.ones(n, dtype=torch.bool) if semantic_dynamic is None else semantic_dynamic.bool().cpu()
        self.register_buffer("dynamic_index", torch.nonzero(dyn).flatten())
        self.register_buffer("static_index", torch.nonzero(~dyn).flatten())
        gen = torch.Generator().manual_seed(seed)
        base = static_features.detach().float().cpu()
        # Layout [N_dyn, K, D]: state k of Gaussian n is base[n] + noise (the release scrambled this
        # by viewing a [K, N, D] tensor as [N, K, D]).
        noise = cfg.init_noise * torch.randn(len(self.dynamic_index), cfg.num_states, d, generator=gen)
        self.states = nn.Parameter(base[self.dynamic_index][:, None, :] + noise)
        self.fixed = nn.Parameter(base[self.static_index].clone())
        self.weight_mlp = nn.Sequential(nn.Linear(hexplane_dim, cfg.hidden_dim), nn.ReLU(),
                                        nn.Linear(cfg.hidden_dim, cfg.num_states))
        self.num_gaussians = n
        self.latent_dim = d
        position = torch.full((n,), -1, dtype=torch.long)
        position[self.dynamic_index] = torch.arange(len(self.dynamic_index))
        position[self.static_index] = -2 - torch.arange(len(self.static_index))  # static k at -2 - k
        self.register_buffer("_position", position, persistent=False)

    def weights(self, hexplane_features: torch.Tensor) -> torch.Tensor:
        """[N_dyn, F] HexPlane features of the dynamic Gaussians -> [N_dyn, K] state weights."""
        logits = self.weight_mlp(hexplane_features)
        if self.cfg.weight_mode != "softmax":
            return logits
        # the same softmax over each row's K states, taken over a [K, N] copy: torch's CPU softmax along a
        # last axis of 2-6 elements is several times slower than along a long leading one
        return torch.softmax(logits.t().contiguous(), dim=0).t()

    def weight_entropy(self, hexplane_features: torch.Tensor) -> torch.Tensor:
        """Mean entropy (nats) of the softmax weights of the dynamic Gaussians at (x, t): 0 when each
        Gaussian is in exactly one state, ln K for an even mix. Softmax mode only."""
        if self.cfg.weight_mode != "softmax" or hexplane_features.shape[0] == 0:
            return hexplane_features.new_zeros(())
        logp = torch.log_softmax(self.weight_mlp(hexplane_features), dim=-1)
        return -(logp.exp() * logp).sum(-1).mean()

    def forward(self, hexplane_features: torch.Tensor) -> torch.Tensor:
        """[N_dyn, F] HexPlane features at (x, t) of the dynamic Gaussians -> [N, D] features at t."""
        w = self.weights(hexplane_features)  # [N_dyn, K]
        dyn_feat = torch.einsum("nk,nkd->nd", w, self.states)
        out = self.states.new_empty(self.num_gaussians, self.latent_dim)
        out[self.dynamic_index] = dyn_feat
        out[self.static_index] = self.fixed
        return out

    def plan(self, rows: torch.Tensor) -> RowPlan:
        """The :class:`RowPlan` of ``rows`` (global Gaussian ids)."""
        position = self._position[rows]
        dynamic = position >= 0
        return RowPlan(rows, position[dynamic], torch.nonzero(dynamic).flatten(), torch.nonzero(~dynamic).flatten(),
                       -2 - position[~dynamic])

    def forward_rows(self, hexplane_features: torch.Tensor, plan: RowPlan) -> torch.Tensor:
        """:meth:`forward` on ``plan.rows`` only: [M, F] HexPlane features of its dynamic rows
        (``plan.hexplane_index`` of the module's input) -> [R, D] features at t of ``plan.rows``."""
        w = self.weights(hexplane_features)
        dyn_feat = torch.einsum("nk,nkd->nd", w, self.states[plan.hexplane_index])
        out = self.states.new_empty(len(plan.rows), self.latent_dim)
        out[plan.dynamic_at] = dyn_feat
        out[plan.static_at] = self.fixed[plan.static_index]
        return out

    def parameter_bytes(self) -> int:
        """Bytes of per-Gaussian and network parameters (for the memory-per-Gaussian report)."""
        return sum(p.numel() * p.element_size() for p in self.parameters())


class NonStatusField(nn.Module):
    """Baseline: ``f(x, t) = f_static + MLP(hexplane(x, t))`` for every Gaussian."""

    def __init__(self, static_features: torch.Tensor, hexplane_dim: int, hidden_dim: int = 64):
        """
        Args:
            static_features: [N, D] initial latent feature of every Gaussian.
            hexplane_dim:    F, dimension of the HexPlane feature.
        """
        super().__init__()
        self.static = nn.Parameter(static_features.detach().float().clone())
        d = static_features.shape[1]
        self.delta_mlp = nn.Sequential(nn.Linear(hexplane_dim, hidden_dim), nn.ReLU(),
                                       nn.Linear(hidden_dim, d))
        nn.init.zeros_(self.delta_mlp[-1].weight)  # start at the static feature
        nn.init.zeros_(self.delta_mlp[-1].bias)

    def forward(self, hexplane_features: torch.Tensor) -> torch.Tensor:
        """[N, F] HexPlane features at (x, t) -> [N, D] features at t."""
        return self.static + self.delta_mlp(hexplane_features)

    def plan(self, rows: torch.Tensor) -> RowPlan:
        """The :class:`RowPlan` of ``rows`` (every Gaussian reads its HexPlane feature)."""
        return RowPlan(rows, rows)

    def forward_rows(self, hexplane_features: torch.Tensor, plan: RowPlan) -> torch.Tensor:
        """:meth:`forward` on ``plan.rows`` only ([R, F] their HexPlane features -> [R, D])."""
        return self.static[plan.rows] + self.delta_mlp(hexplane_features)

    def parameter_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.parameters())
