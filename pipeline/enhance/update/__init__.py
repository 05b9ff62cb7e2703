"""Moving vertices to the corrected depth: the view steps (`steps`, which picks `steps_numpy`
or `steps_torch`), each vertex's gain, the bilateral normal filter."""
