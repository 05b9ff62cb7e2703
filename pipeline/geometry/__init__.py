"""Geometry every stage shares: the triangle mesh, its canonical order, repairs, open boundaries
and the classical smoothers."""
