"""The remesh stage: isotropic remeshing (its kernel in child processes, in spatial pieces), long
boundary edges split first, angles cleaned up after, and the speculative remesh."""
