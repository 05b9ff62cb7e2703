from pathlib import Path

import pytest

from app.cli.paths import output_file, output_folder


def test_an_output_files_missing_folders_are_made(tmp_path: Path) -> None:
    out = tmp_path / "a" / "b" / "mesh.ply"
    assert output_file(out) == out
    assert out.parent.is_dir() and not out.exists()


def test_a_folder_or_an_unmakeable_folder_is_refused_naming_the_option(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"^--report: .* is a directory"):
        output_file(tmp_path, "--report")
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match=r"^--out: cannot make the folder .*file"):
        output_file(tmp_path / "file" / "mesh.ply")


def test_an_output_folder_is_made_and_a_file_in_its_place_refused(tmp_path: Path) -> None:
    out = tmp_path / "a" / "b"
    assert output_folder(out).is_dir()
    assert output_folder(out) == out  # already there: fine
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match=r"^--out: .*file is a file; give a folder"):
        output_folder(tmp_path / "file")
    with pytest.raises(ValueError, match=r"^--out: cannot make the folder .*file.*x"):
        output_folder(tmp_path / "file" / "x")


def test_an_output_file_without_a_wanted_suffix_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"^--out: .*mesh.obj must end in .glb or .ply$"):
        output_file(tmp_path / "mesh.obj", suffixes=(".glb", ".ply"))
    assert output_file(tmp_path / "mesh.GLB", suffixes=(".glb", ".ply")).name == "mesh.GLB"
