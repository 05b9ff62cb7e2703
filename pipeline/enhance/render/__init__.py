"""Orthographic depth renders of a mesh from several directions: `views.render_depth` picks
open3d's ray cast (`ray_cast`, on the host) or the torch rasterizer (`rasterize`, on a
device); both share the cameras and render types of `camera`."""
