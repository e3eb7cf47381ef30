"""Tools that drive many runs of the testbed: sweeps (and later bench, regress, reports)."""
