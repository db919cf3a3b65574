"""Every document the repository cites is in the repository, with the section it cites.

Code, tests and documents cite the project's documents as ``docs/pipeline.md section 7`` (also
``sections 5 and 7``, ``sections 1-8``, ``sections 1.7 and 3``, across a line break or a ``#``
comment). A citation names a path relative to the repository root; the file must exist and, for
each section number cited, hold a Markdown heading that starts with that number (``## 7.`` or
``### 7.2``). Nothing may cite the design notes that once lived beside the repository: the
repository stands alone.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCANNED_SUFFIXES = (".py", ".md", ".toml")
SKIPPED_DIRS = {"__pycache__", "node_modules", "build", "dist"}

NUMBER = r"\d+(?:\.\d+)*"
CITATION = re.compile(
    r"(?<![\w./-])(?P<path>(?:[\w.-]+/)+[\w.-]+\.md)"  # a repository-relative path with a folder
    r"[`*\])]*(?:\s|#|\"|')*"  # closing code or emphasis marks, spaces, a line break, a comment mark
    rf"sections?\s+(?P<numbers>{NUMBER}(?:\s*(?:,|and|-|–|to)\s*{NUMBER})*)"
)
"""``PATH.md section N`` and its list and range forms."""
DOCUMENT = re.compile(r"(?<![\w./-])(?P<path>docs/[\w.-]+\.md)")
"""Any mention of a document under docs/, cited by section or not."""
HEADING = re.compile(rf"^#{{1,6}}\s+(?P<number>{NUMBER})\.?(?:\s|$)", re.MULTILINE)

# Spelled in pieces so that this file does not match its own rules.
OUTSIDE = "../" + "shared"
FORBIDDEN = re.compile(
    "|".join(
        [
            re.escape(OUTSIDE + "/design"),
            re.escape(OUTSIDE + "/reference"),
            r"(?<![\w-])" + "PIPE" + r"LINE\.md",
            "authors-" + r"pipeline\.md",
            "air-osvp-" + r"paper\.tex",
            r"(?<![\w./-])" + "limits" + r"\.md",
        ]
    )
)
"""The external design contract, the authors' notes, the paper's source and the cost notes."""


def repository_files() -> list[Path]:
    """Tracked and not-ignored files (git), or a walk of the tree where there is no git checkout."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        ).stdout.decode()
        names = [name for name in listed.split("\0") if name]
    except (OSError, subprocess.CalledProcessError):
        names = []
        for folder, dirs, files in os.walk(ROOT):
            dirs[:] = [d for d in dirs if not d.startswith(".") and d not in SKIPPED_DIRS and "egg-info" not in d]
            names.extend(os.path.relpath(os.path.join(folder, f), ROOT) for f in files)
    paths = [ROOT / name for name in names if name.endswith(SCANNED_SUFFIXES)]
    return sorted(p for p in paths if p.is_file() and p.resolve() != Path(__file__).resolve())


def section_numbers(text: str) -> set[str]:
    return {match["number"] for match in HEADING.finditer(text)}


def cited_sections(numbers: str) -> list[str]:
    """The section numbers a citation names; a range names both ends and, for whole sections, all
    between (``1-8`` is 1 to 8; ``1.6-3`` is 1.6 and 3)."""
    cited: list[str] = []
    for part in re.split(r"\s*(?:,|and)\s*", numbers):
        ends = re.split(r"\s*(?:-|–|to)\s*", part)
        if len(ends) == 2 and ends[0].isdigit() and ends[1].isdigit():
            cited.extend(str(n) for n in range(int(ends[0]), int(ends[1]) + 1))
        else:
            cited.extend(ends)
    return cited


def citation_problems(texts: list[tuple[str, str]]) -> list[str]:
    """What is wrong with the citations of each (file name, text)."""
    problems: list[str] = []
    headings: dict[str, set[str] | None] = {}

    def sections_of(path: str) -> set[str] | None:
        if path not in headings:
            target = ROOT / path
            headings[path] = section_numbers(target.read_text(encoding="utf-8")) if target.is_file() else None
        return headings[path]

    for where, text in texts:
        for match in FORBIDDEN.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            problems.append(f"{where}:{line}: cites {match.group()!r}, outside the repository; cite docs/ instead")
        for match in DOCUMENT.finditer(text):
            if sections_of(match["path"]) is None:
                line = text.count("\n", 0, match.start()) + 1
                problems.append(f"{where}:{line}: cites {match['path']}, which does not exist")
        for match in CITATION.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            sections = sections_of(match["path"])
            if sections is None:
                problems.append(f"{where}:{line}: cites {match['path']}, which does not exist")
                continue
            for number in cited_sections(match["numbers"]):
                if number not in sections:
                    problems.append(
                        f"{where}:{line}: cites {match['path']} section {number}, which has no such heading"
                    )
    return sorted(set(problems))


def test_the_documents_exist() -> None:
    for name in ("pipeline", "authors-code"):
        assert (ROOT / "docs" / f"{name}.md").is_file(), f"docs/{name}.md is missing"


def test_every_citation_resolves_inside_the_repository() -> None:
    files = repository_files()
    assert any(f.name == "setcover.py" for f in files), "the scan found none of the pipeline's files"
    problems = citation_problems(
        [(str(f.relative_to(ROOT)), f.read_text(encoding="utf-8", errors="replace")) for f in files]
    )
    assert not problems, "\n".join(problems)


def test_the_pipeline_contract_numbers_its_sections() -> None:
    sections = section_numbers((ROOT / "docs" / "pipeline.md").read_text(encoding="utf-8"))
    assert {str(n) for n in range(10)} <= sections


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("see docs/pipeline.md section 7.", []),
        ("(docs/pipeline.md sections 1.7 and 3)", []),
        ("docs/pipeline.md sections 1-8", []),
        ("docs/pipeline.md\nsection 42", ["docs/pipeline.md section 42"]),
        ('"""Labels (docs/pipeline.md section 7.9, more)', ["docs/pipeline.md section 7.9"]),
        ("# docs/authors-code.md sections 8.2 and 8.7", ["docs/authors-code.md section 8.7"]),
        ("docs/pipeline.md sections 8-11", ["docs/pipeline.md section 10", "docs/pipeline.md section 11"]),
        ("docs/nowhere.md section 1", ["docs/nowhere.md, which does not exist"]),
        ("docs/nowhere.md", ["docs/nowhere.md, which does not exist"]),
        (OUTSIDE + "/design/X.md", ["outside the repository"]),
        ("design/" + "PIPE" + "LINE.md section 6", ["outside the repository"]),
        ("reference/authors-" + "pipeline.md section 8.2", ["outside the repository"]),
        ("the authors' notes (authors-" + "pipeline.md 7.2)", ["outside the repository"]),
        ("`reference/air-osvp-" + "paper.tex`", ["outside the repository"]),
    ],
)
def test_a_bad_citation_fails(text: str, expected: list[str]) -> None:
    """The checker itself: good citations pass, each kind of bad one is named."""
    problems = citation_problems([("probe.md", text)])
    assert bool(problems) == bool(expected), problems
    for fragment in expected:
        assert any(fragment in problem for problem in problems), problems
