"""File I/O of the pipeline: captures in, meshes and reports out. Nothing else touches files."""
