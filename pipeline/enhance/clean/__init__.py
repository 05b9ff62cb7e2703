"""The light remesh that ends the enhancement, and its transfer onto the moved mesh."""
