"""One spec module per registered method (each defines ``SPEC``), discovered by
:mod:`methods.registry`; :mod:`.paper_numbers` holds the paper's numbers as data."""
