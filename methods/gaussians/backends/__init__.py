"""Rasterizer backends behind :func:`methods.gaussians.rasterize.rasterize`.

* :mod:`.torch_cpu` -- pure PyTorch, sparse compositing (default on CPU, any device works).
* :mod:`.gsplat_cuda` -- ``gsplat.rasterization`` on CUDA tensors, where gsplat is installed.
"""
