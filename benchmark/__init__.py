"""bench4d: the open benchmark for open-vocabulary 4D language fields.

The harness: scene data model (:mod:`benchmark.core.scene`), loaders (:mod:`benchmark.loaders`),
the synthetic 4D scene generator (:mod:`benchmark.synthetic`), the metrics core
(:mod:`benchmark.metrics`), and the CLI ``bench4d`` (:mod:`benchmark.cli`).
"""

__version__ = "0.1.0"

from benchmark.core.openblas import pin_before_numpy

# Before anything loads numpy: generated scenes depend on its BLAS kernels (see benchmark.core.openblas).
pin_before_numpy()
