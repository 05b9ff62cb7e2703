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


def accelerator(device: str | None) -> str | None:
    """`device` where it is an accelerator, None for the CPU: the geometry stages ported to
    torch for the GPU (`mesh_torch` and its users) stay in numpy and scipy on the CPU, where
    they are as fast."""
    return None if device in (None, "cpu") else device


def on_device(array: NDArray, device: str) -> torch.Tensor:
    """A numpy array as a tensor on `device`, its dtype kept."""
    return torch.from_numpy(np.ascontiguousarray(array)).to(device)


def csr_tensor(row_starts: torch.Tensor, columns: torch.Tensor, values: torch.Tensor,
               shape: tuple[int, int]) -> torch.Tensor:
    """A sparse CSR tensor of `row_starts` and `columns` (both int32, or both int64) on
    `values`' device, without torch's beta warning or its invariant checks (the callers
    build valid rows)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(row_starts, columns, values, size=shape,
                                       check_invariants=False)


def csr_on_device(matrix: sp.csr_matrix, device: str) -> torch.Tensor:
    """A scipy CSR matrix as a torch sparse CSR tensor on `device`, with `csr_indices`."""
    return csr_tensor(*csr_indices(matrix.indptr, matrix.indices, device),
                      on_device(matrix.data, device), matrix.shape)


def csr_indices(row_starts: NDArray, columns: NDArray, device: str
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """CSR row starts and columns on `device`, int32 where they fit: sparse products then read
    half the index bytes."""
    dtype = np.int32 if row_starts[-1] < np.iinfo(np.int32).max else np.int64
    return on_device(row_starts.astype(dtype), device), on_device(columns.astype(dtype), device)
