"""The reconstruction stages, one module each: depth filter, registration, alignment, crop, voxel
refinement, meshing, remesh, colour."""
