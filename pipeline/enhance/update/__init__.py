"""Moving vertices to the corrected depth: the view steps, each vertex's gain, the bilateral normal
filter."""
