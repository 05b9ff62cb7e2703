"""Orthographic depth renders of a mesh from several directions."""
