"""The torch device a run or an inference uses."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import torch
from numpy.typing import NDArray


def resolve_device(name: str) -> torch.device:
    """'auto' (CUDA when present, else CPU), 'cpu' or 'cuda'."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda"):
        raise ValueError(f"device: {name!r} is not one of auto, cpu, cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device: cuda requested but no CUDA device is available")
    return torch.device(name)


def on_device(array: NDArray, device: str) -> torch.Tensor:
    """A numpy array as a tensor on `device`, its dtype kept."""
    return torch.from_numpy(np.ascontiguousarray(array)).to(device)


def csr_tensor(row_starts: torch.Tensor, columns: torch.Tensor, values: torch.Tensor,
               shape: tuple[int, int]) -> torch.Tensor:
    """A sparse CSR tensor of int64 `row_starts` and `columns` on `values`' device, without
    torch's beta warning or its invariant checks (the callers build valid rows)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(row_starts, columns, values, size=shape,
                                       check_invariants=False)


def csr_on_device(matrix: sp.csr_matrix, device: str) -> torch.Tensor:
    """A scipy CSR matrix as a torch sparse CSR tensor on `device`."""
    return csr_tensor(on_device(matrix.indptr.astype(np.int64), device),
                      on_device(matrix.indices.astype(np.int64), device),
                      on_device(matrix.data, device), matrix.shape)
