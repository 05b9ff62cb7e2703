"""Output paths of the commands, checked before their work starts."""

from __future__ import annotations

from pathlib import Path


def output_file(path: Path, option: str = "--out", suffixes: tuple[str, ...] = ()) -> Path:
    """`path`, its folder made where it is missing, so that a long run does not end on a path
    it cannot write; a ValueError naming `option` where it does not end in one of `suffixes`
    (any, where none are given), is a folder or its folder cannot be made."""
    if suffixes and path.suffix.lower() not in suffixes:
        raise ValueError(f"{option}: {path} must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise ValueError(f"{option}: {path} is a directory; give a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{option}: cannot make the folder {path.parent} ({exc.strerror})"
                         ) from exc
    return path


def output_folder(path: Path, option: str = "--out") -> Path:
    """`path`, made with its parents where missing; a ValueError naming `option` where it is
    a file or cannot be made."""
    if path.exists() and not path.is_dir():
        raise ValueError(f"{option}: {path} is a file; give a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{option}: cannot make the folder {path} ({exc.strerror})") from exc
    return path
