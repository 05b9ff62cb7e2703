"""Pre-smoothing ahead of the depth networks: twicing with scale selection
(`scale_selection`), then the midrange estimator (`midrange`). Each picks its numpy
(`*_numpy`) or torch (`*_torch`) implementation by device; the two share a `*_common` module
and never import each other."""
