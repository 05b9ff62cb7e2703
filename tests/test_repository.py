"""The repository's documents stand on their own: every link and every file path they name is
in the repository, and none points beside it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = sorted([ROOT / "README.md", ROOT / "pipeline/enhance/weights/MODEL_CARD.md",
                    *(ROOT / "docs").rglob("*.md")])
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
CODE_PATH = re.compile(
    r"`((?:app|workers|pipeline|benchmarks|tests|static|docs|agent)/[\w/.\-]+"
    r"\.(?:py|md|json|js|sh|html|css))`")
FOUNDING_DOCUMENTS = re.compile(r"DESIGN\.md|CAPTURE_FORMAT\.md|WEB_NOTES\.md")


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


@pytest.mark.parametrize("document", DOCUMENTS, ids=_name)
def test_every_link_and_named_file_is_in_the_repository(document: Path) -> None:
    text = document.read_text()
    links = [m.group(1) for m in LINK.finditer(text)
             if not m.group(1).startswith(("http://", "https://", "mailto:"))]
    missing = [link for link in links if not (document.parent / link).resolve().is_relative_to(
        ROOT) or not (document.parent / link).exists()]
    missing += [path for path in CODE_PATH.findall(text) if not (ROOT / path).exists()]
    assert not missing, f"{_name(document)} names what the repository does not hold: {missing}"


@pytest.mark.parametrize("document", DOCUMENTS, ids=_name)
def test_no_document_sends_the_reader_outside_the_repository(document: Path) -> None:
    assert not FOUNDING_DOCUMENTS.search(document.read_text())


def test_no_code_points_at_the_founding_documents() -> None:
    sources = [p for folder in ("app", "workers", "pipeline", "agent", "static", "benchmarks")
               for p in (ROOT / folder).rglob("*") if p.suffix in (".py", ".js", ".html", ".sh")]
    pointing = [_name(p) for p in sources if FOUNDING_DOCUMENTS.search(p.read_text())]
    assert not pointing


SOURCE_FOLDERS = ("app", "workers", "pipeline", "agent", "benchmarks", "tests")
MAX_MODULE_LINES = 400
NARRATIVE = re.compile(r"\b(?:\w+(?:st|nd|rd|th)|earlier|later|this|last) session\b", re.I)


def _sources() -> list[Path]:
    return [p for folder in SOURCE_FOLDERS for p in (ROOT / folder).rglob("*.py")
            if ".venv" not in p.parts]


def test_no_module_is_over_400_lines() -> None:
    long = {_name(p): n for p in _sources()
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long


def test_code_and_documents_tell_no_story_of_sessions() -> None:
    told = [_name(p) for p in [*_sources(), *DOCUMENTS] if NARRATIVE.search(p.read_text())]
    assert not told
