"""Pre-smoothing ahead of the depth networks: twicing with scale selection, then the midrange
estimator."""
