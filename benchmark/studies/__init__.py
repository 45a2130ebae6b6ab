"""Experiments on top of the harness and the methods, one module per study: the perfect-feature
ceiling, the field gap, and the ablations, measurements and sweeps behind ``bench4d ablate``. Nothing in
the harness or the methods imports them."""
