"""The order in which a per-Gaussian field fit visits its training views, on a frozen geometry."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .language_field import FrozenGeometry, GaussianState


class ViewCycle:
    """Training views in epochs of a seeded random order (each view once per epoch); each view's deformed
    Gaussians are computed once and kept while all of them fit in ``budget_bytes`` (the geometry is frozen,
    so they never change)."""

    def __init__(self, geometry: FrozenGeometry, times: Sequence[float], seed: int, budget_bytes: float) -> None:
        if not len(times):
            raise ValueError("a field fit needs at least one training view")
        self.geometry = geometry
        self.times = list(times)
        self._rng = np.random.default_rng(seed)
        self._order: list[int] = []
        self._states: dict[int, GaussianState] = {}
        self._keep = (not geometry.is_dynamic
                      or geometry.at(self.times[0]).nbytes() * len(self.times) <= budget_bytes)

    def next(self) -> tuple[int, GaussianState]:
        """(index of the next view, the Gaussians at its time)."""
        if not self._order:
            self._order = self._rng.permutation(len(self.times)).tolist()
        view = self._order.pop()
        state = self._states.get(view)
        if state is None:
            state = self.geometry.at(self.times[view])
            if self._keep:
                self._states[view] = state
        return view, state
