"""Training the enhancement's networks: data, stages, loops and the per-vertex networks' fits."""
