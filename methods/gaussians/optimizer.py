"""Adam over the Gaussian tensors, whose moments follow densification (one row per Gaussian)."""

from __future__ import annotations

import torch

from .config import GaussianConfig
from .model import PARAM_NAMES, GaussianModel


def fast_adam(params, **kwargs) -> torch.optim.Adam:
    """:class:`torch.optim.Adam` with its fused update (one kernel per step instead of a dozen passes per
    tensor; several times faster on the CPU) where this torch has it for the parameters' device, else
    the plain one: the same algorithm, rounded in another order."""
    params = list(params)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, **kwargs)


class GaussianOptimizer:
    """Adam over the Gaussian tensors, one group per tensor, whose moments follow densification."""

    def __init__(self, model: GaussianModel, cfg: GaussianConfig, extent: float):
        self.model = model
        lrs = {"means": cfg.position_lr_init * extent, "sh_dc": cfg.feature_lr,
               "sh_rest": cfg.feature_lr / cfg.feature_rest_lr_divisor, "opacity_logits": cfg.opacity_lr,
               "log_scales": cfg.scaling_lr, "quats": cfg.rotation_lr}
        self.optim = fast_adam([{"params": [model.params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES],
                               lr=0.0, eps=cfg.adam_eps)
        self.groups = {g["name"]: g for g in self.optim.param_groups}

    def set_lr(self, name: str, lr: float) -> None:
        self.groups[name]["lr"] = lr

    def load_state_dict(self, state: dict) -> None:
        """Moments and learning rates as saved (torch replaces the group dicts: ``groups`` follows)."""
        self.optim.load_state_dict(state)
        self.groups = {g["name"]: g for g in self.optim.param_groups}

    def step(self) -> None:
        self.optim.step()
        self.optim.zero_grad(set_to_none=True)

    def rebuild(self, new_values: dict[str, torch.Tensor], keep_rows: torch.Tensor, n_added: int) -> None:
        """Replace every tensor by ``new_values[name]`` whose rows are ``old[keep_rows]`` followed by
        ``n_added`` new rows; Adam moments follow the kept rows and start at zero for new ones."""
        for name in PARAM_NAMES:
            group = self.groups[name]
            old = group["params"][0]
            new = new_values[name].detach().contiguous().requires_grad_(True)
            state = self.optim.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    moment = state[key][keep_rows]
                    pad = moment.new_zeros((n_added,) + moment.shape[1:])
                    state[key] = torch.cat([moment, pad], 0)
                self.optim.state[new] = state
            group["params"][0] = new
            self.model.params[name] = new

    def reset_moments(self, name: str) -> None:
        state = self.optim.state.get(self.groups[name]["params"][0])
        if state:
            state["exp_avg"].zero_()
            state["exp_avg_sq"].zero_()
