"""volumesh's 3D and ML library: pure functions on arrays, one stage per module."""
