"""One spec module per supervision source (each defines ``SPEC``); discovered by
:mod:`methods.supervision.registry`. Spec modules import nothing heavy."""
