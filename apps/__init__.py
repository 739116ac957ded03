"""Console entry points that compose the packages: ``dit-slam`` (runtime, and sim for the default sequence) and
``dit-eval`` (runtime's trajectory evaluation, train's depth evaluation)."""
