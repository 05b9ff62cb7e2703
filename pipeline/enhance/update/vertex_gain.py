"""How much of the networks' correction each vertex follows, from what the views say about it.

Whether a vertex's correction is worth following shows across the views that see it: views
that agree, and a step of the size the remaining noise has, are trusted more than one view's
lone large step. A small network (`models/vertex_gain.py`, trained by `training/gain.py`)
reads these features and gives each vertex its own gain, in place of one share for all.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.enhance.update.steps_common import ViewSteps

GAIN_FEATURES = 4
"""Per-vertex features: mean step along the normal, its spread over the views (both in edge
lengths), the views' summed weight and the share of the views that see the vertex (both per
view, so that more views than the six the gains were trained with read alike)."""
MEAN_STEP = 0
"""Column of the mean step along the normal: what a vertex's gain scales."""


def gain_features(steps: ViewSteps, edge_m: float) -> NDArray[np.float32]:
    """(V, GAIN_FEATURES) features of each vertex's view steps (`GAIN_FEATURES`' order);
    lengths over `edge_m`, the mesh's mean edge length, so they do not depend on its scale."""
    along = steps.along_normals_m() / edge_m
    w = steps.weights
    total = w.sum(axis=0)
    safe = np.maximum(total, 1e-12)
    mean = (w * along).sum(axis=0) / safe
    spread = np.sqrt((w * (along - mean) ** 2).sum(axis=0) / safe)
    views = len(w)
    share = (w > 0).sum(axis=0) / views
    return np.stack([mean, spread, total / views, share], axis=1).astype(np.float32)

