"""The order in which a per-Gaussian field fit visits its training views, on a frozen geometry."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from benchmark.core.scene import Camera

from .language_field import FrozenGeometry, GaussianState


class ViewCycle:
    """Training views in epochs of a seeded random order (each view once per epoch); each view's deformed
    Gaussians are computed once and kept while all of them fit in ``budget_bytes`` (the geometry is frozen,
    so they never change)."""

    def __init__(self, geometry: FrozenGeometry, times: Sequence[float], seed: int, budget_bytes: float, *,
                 cameras: Optional[Sequence[Camera]] = None, near: float = 0.01, render_backend: str = "auto",
                 matrix_budget_bytes: float = 0.0) -> None:
        """``cameras`` (one per time) turn on :meth:`prepared`: each view's rendering kept as its blending matrix
        while all of them fit ``matrix_budget_bytes``, else as its projection and tile layout while those fit
        ``budget_bytes``."""
        if not len(times):
            raise ValueError("a field fit needs at least one training view")
        self.geometry = geometry
        self.times = list(times)
        self._rng = np.random.default_rng(seed)
        self._order: list[int] = []
        self._states: dict[int, GaussianState] = {}
        self._keep = (not geometry.is_dynamic
                      or geometry.at(self.times[0]).nbytes() * len(self.times) <= budget_bytes)
        if cameras is not None and len(cameras) != len(self.times):
            raise ValueError(f"{len(cameras)} cameras for {len(self.times)} views")
        self._cameras = None if cameras is None else list(cameras)
        self._near, self._backend = near, render_backend
        self._budget, self._matrix_budget = budget_bytes, matrix_budget_bytes
        self._views: dict[int, object] = {}
        self._matrices: Optional[bool] = None  # decided on the first view prepared
        self.rendered_by = "rasterizer"
        """How :meth:`prepared` renders: ``"rasterizer"``, ``"kept layouts"`` or ``"blend matrices"``."""

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

    def prepared(self, view: int, state: GaussianState):
        """View ``view``'s rendering with the Gaussians ``state`` fixed, for any colours: a
        :class:`~methods.fields.language_field.BlendMatrixView` (a sparse matrix product) where every view's
        matrix fits the matrix budget, else the rasterizer's frozen view (:func:`methods.gaussians.rasterize.prepare_view`,
        kept while every view's fits the geometry budget); ``None`` without cameras, or where the rasterizer has
        no such split (CUDA, gsplat, no C compiler): render with the rasterizer then. Both give the rasterizer's
        numbers up to float rounding."""
        if self._cameras is None:
            return None
        kept = self._views.get(view)
        if kept is not None:
            return kept
        from methods.gaussians.rasterize import camera_tensors, prepare_view

        from .language_field import BlendMatrixView

        viewmat, K, w, h = camera_tensors(self._cameras[view], state.means.device)
        frozen = prepare_view(state.means, state.quats, state.scales, state.opacities, viewmat, K, w, h,
                              near=self._near, backend=self._backend)
        if frozen is None:
            return None
        if self._matrices is None:  # views differ in size by the Gaussians each sees: a margin over the first
            matrix = BlendMatrixView.from_frozen(frozen) if self._matrix_budget > 0 else None
            self._matrices = matrix is not None and 1.25 * matrix.nbytes() * len(self.times) <= self._matrix_budget
            if self._matrices:
                frozen = matrix
        elif self._matrices:
            frozen = BlendMatrixView.from_frozen(frozen)
        if self._matrices or frozen.nbytes() * len(self.times) <= self._budget:
            self._views[view] = frozen
            self.rendered_by = "blend matrices" if self._matrices else "kept layouts"
        return frozen
