"""The shipped weights (safetensors) and their model card, read as package data."""

from __future__ import annotations

from importlib import resources

DEFAULT_FILES = {
    "regressor": "regressor.safetensors",
    "vae": "vae.safetensors",
    "ldm": "ldm.safetensors",
    "selector": "selector.safetensors",
    "ldm_gain": "ldm_gain.safetensors",
    "regressor_gain": "regressor_gain.safetensors",
}


def shipped_bytes(name: str) -> bytes:
    """The bytes of a shipped weights file (`DEFAULT_FILES`' keys).

    Raises ValueError when the package was built without it.
    """
    if name not in DEFAULT_FILES:
        raise ValueError(
            f"weights: unknown model {name!r}; expected one of {sorted(DEFAULT_FILES)}"
        )
    ref = resources.files(__package__).joinpath(DEFAULT_FILES[name])
    if not ref.is_file():
        raise ValueError(f"weights: {DEFAULT_FILES[name]} is not shipped with this package")
    return ref.read_bytes()
