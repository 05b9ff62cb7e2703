"""LDM mesh enhancement: depth views of a mesh are enhanced and the vertices
follow them. The only package that imports torch (lazily, inside functions)."""

from pipeline.enhance.config import EnhanceConfig
from pipeline.enhance.enhancement import enhance_mesh

__all__ = ["EnhanceConfig", "enhance_mesh"]
