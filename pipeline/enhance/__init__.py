"""Mesh enhancement: a mesh is pre-smoothed, a depth network (LDM or regressor) corrects its
depth views and the vertices follow them; `classical` runs the same without the network. The
only package that imports torch."""

from pipeline.enhance.config import EnhanceConfig
from pipeline.enhance.enhancement import enhance_mesh

__all__ = ["EnhanceConfig", "enhance_mesh"]
