"""Every name the README and docs/ give a reader is real: paths, modules and commands.

Documents go stale silently when code moves: a renamed module, a deleted file, a command folded into
another. This test reads ``README.md`` and every ``docs/**/*.md`` and checks three kinds of name:

- **paths**: a repository path in backticks (or in a shell code block's command line), one that starts
  at an entry of the repository root, contains a ``/`` and ends in a known suffix or in ``/``, exists
  relative to the repository root (paths that start elsewhere name the authors' files or a dataset's
  own folders and are left alone); every relative Markdown link target exists relative to the
  document, and its ``#anchor``, where it has one, names a heading of the target. URLs with a
  scheme, absolute or home paths (``/tmp/...``, ``~/.datagen``), paths under ``../shared``,
  placeholders in capitals (``DIR/``, ``URL``) and anything with ``*``, ``<``, ``{`` or ``$`` are
  left alone;
- **modules**: a dotted name in backticks that starts with ``datagen.``, ``storage.``, ``schemas.``,
  ``osvp.``, ``jobs.`` or ``benchmarks.`` resolves: its longest importable prefix is a module
  (`importlib.util.find_spec`) and the rest are attributes of it (``storage.open_dataset``,
  ``osvp.planning:load_scorer``); an entry-point group (``datagen.planners``) is not a module. The
  imports of Python code blocks and every ``python -m MODULE`` resolve the same way;
- **commands**: every ``datagen COMMAND [SUBCOMMAND]`` and ``osvp COMMAND`` in backticks or a shell
  code block answers ``--help`` with exit status 0 (typer and argparse answer 2 for an unknown one),
  each distinct command run once.

A failure lists each stale name with its document and line.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
PATH_SUFFIXES = (".py", ".md", ".sh", ".toml", ".txt", ".yml", ".yaml")
MODULE_ROOTS = ("datagen", "storage", "schemas", "osvp", "jobs", "benchmarks")
SHELL_LANGUAGES = {"", "bash", "sh", "shell", "console", "text"}
PYTHON_LANGUAGES = {"python", "py", "pycon"}

FENCE = re.compile(r"^\s*(```+|~~~+)\s*([\w+-]*)")
INLINE_CODE = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", re.DOTALL)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^()\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_LINK = re.compile(r"^\s*\[[^\]]+\]:\s*(\S+)", re.MULTILINE)
HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_-]*$")
MODULE_NAME = re.compile(
    rf"(?<![\w./:-])((?:{'|'.join(MODULE_ROOTS)})(?:\.[A-Za-z_]\w*)+)(?::([A-Za-z_]\w*))?(?![\w-])"
)
COMMAND = re.compile(r"(?<![\w./:=$-])(datagen|osvp)[ \t]+([a-z][\w-]*)(?:[ \t]+([a-z][\w-]*))?")
PYTHON_M = re.compile(r"(?<![\w-])python3?[ \t]+-m[ \t]+([A-Za-z_][\w.]*)(?![.<\w])")
PYTHON_IMPORT = re.compile(r"^\s*(?:from\s+([\w.]+)\s+import\s+\(?([\w\s,]+)\)?|import\s+([\w.]+))", re.MULTILINE)


@dataclass(frozen=True)
class Mention:
    """One name as a document writes it: where, and in what (inline code, link, code block)."""

    where: str
    line: int
    text: str
    kind: str
    """``code`` (inline code), ``link`` (a link target), ``block:LANG`` (a line of a fenced block)."""


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def blank_out(text: str, start: int, end: int) -> str:
    """``text`` with ``text[start:end]`` replaced by spaces, line breaks kept (line numbers stay)."""
    return text[:start] + re.sub(r"[^\n]", " ", text[start:end]) + text[end:]


def fenced_lines(text: str) -> Iterator[tuple[int, str, str | None]]:
    """Each line of a Markdown text with its number and, inside a fenced code block, the block's
    language (``""`` when it names none); ``None`` for prose and for the fence lines themselves."""
    fence: str | None = None
    language = ""
    for number, line in enumerate(text.split("\n"), start=1):
        opening = FENCE.match(line)
        if fence is None and opening:
            fence, language = opening.group(1), opening.group(2).lower()
            yield number, line, None
        elif fence is not None and re.fullmatch(rf"\s*{re.escape(fence[0])}{{{len(fence)},}}\s*", line):
            fence = None
            yield number, line, None
        else:
            yield number, line, language if fence is not None else None


def mentions(where: str, text: str) -> list[Mention]:
    """Every inline code span, link target and code block line of one Markdown document."""
    found: list[Mention] = []
    prose: list[str] = []
    for number, line, language in fenced_lines(text):
        if language is not None:
            found.append(Mention(where, number, line, f"block:{language}"))
        is_prose = language is None and not FENCE.match(line)
        prose.append(line if is_prose else "")
    body = "\n".join(prose)
    for match in INLINE_CODE.finditer(body):
        code = " ".join(match.group(2).replace("\\|", "|").split())
        found.append(Mention(where, body.count("\n", 0, match.start()) + 1, code, "code"))
    for match in reversed(list(INLINE_CODE.finditer(body))):
        body = blank_out(body, match.start(), match.end())
    for pattern in (LINK, REFERENCE_LINK):
        for match in pattern.finditer(body):
            found.append(Mention(where, body.count("\n", 0, match.start()) + 1, match.group(1), "link"))
    return found


def all_mentions() -> list[Mention]:
    found: list[Mention] = []
    for document in documents():
        found.extend(mentions(str(document.relative_to(ROOT)), document.read_text(encoding="utf-8")))
    return found


# -- paths -------------------------------------------------------------------------------------------


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: its text without links and markup, lower case, punctuation
    dropped, spaces as hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    """The anchors of a Markdown file's headings (outside code blocks), repeats numbered as GitHub does."""
    seen: dict[str, int] = {}
    names: set[str] = set()
    for _, line, language in fenced_lines(path.read_text(encoding="utf-8")):
        heading = HEADING.match(line) if language is None else None
        if heading:
            base = slug(heading.group(2))
            count = seen.get(base, 0)
            seen[base] = count + 1
            names.add(base if count == 0 else f"{base}-{count}")
    return frozenset(names)


def skipped_path(token: str) -> bool:
    """Not a repository path: a URL, an absolute or home path, a placeholder, a pattern, ../shared."""
    if not token or SCHEME.match(token) or token.startswith(("/", "~", "$", "-", "../")):
        return True
    if any(mark in token for mark in "*<>{}$|"):
        return True
    parts = [part for part in token.split("/") if part not in ("", ".", "..")]
    if any(PLACEHOLDER.match(part) for part in parts):
        return True
    return "../shared" in token or token.startswith("shared/")


def looks_like_path(token: str) -> bool:
    return "/" in token and (token.endswith(PATH_SUFFIXES) or token.endswith("/"))


@cache
def root_entries() -> frozenset[str]:
    return frozenset(entry.name for entry in ROOT.iterdir())


def in_repository(token: str) -> bool:
    """A path of this repository: it starts at one of the root's entries. Other paths name files
    elsewhere (the authors' repositories, a dataset's or an export's own folders) and are left alone."""
    parts = [part for part in token.split("/") if part not in ("", ".")]
    return bool(parts) and parts[0] in root_entries()


def path_tokens(text: str) -> Iterator[str]:
    """The words of a code span or command line that may be paths."""
    for word in re.split(r"[\s,;=()\"'`]+", text):
        word = word.rstrip(".:")
        if looks_like_path(word) and not skipped_path(word) and in_repository(word):
            yield word


def path_problems(found: list[Mention]) -> list[str]:
    problems: list[str] = []
    for mention in found:
        if mention.kind == "link":
            target, _, anchor = mention.text.partition("#")
            if SCHEME.match(mention.text) or (target and skipped_path(target)):
                continue
            document = ROOT / mention.where
            resolved = (document.parent / target).resolve() if target else document
            if not resolved.exists():
                problems.append(f"{mention.where}:{mention.line}: link to {mention.text}: no such file")
            elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
                problems.append(f"{mention.where}:{mention.line}: link to {mention.text}: no such heading")
            continue
        if mention.kind.startswith("block:"):
            language = mention.kind.split(":", 1)[1]
            if language not in SHELL_LANGUAGES or mention.text.lstrip().startswith("#"):
                continue  # outputs and comments: paths there are examples
        for token in path_tokens(mention.text):
            if not (ROOT / token).exists():
                problems.append(f"{mention.where}:{mention.line}: path {token}: no such file or folder")
    return problems


# -- modules -----------------------------------------------------------------------------------------


REGISTRY_MODULES = (
    "schemas.objectives",
    "schemas.refiners",
    "storage.export",
    "storage.samples.sample_fields",
    "datagen.evaluate.planners",
    "osvp.architectures",
    "osvp.loss",
    "osvp.decoding",
    "osvp.shipped",
)
"""The modules that make a plug-in registry (`schemas.registry.KINDS`): each names its entry-point group."""


@cache
def entry_point_groups() -> frozenset[str]:
    """The groups installed packages use, and every registry's own (one may have no plug-in installed)."""
    from schemas import registry

    for module in REGISTRY_MODULES:
        importlib.import_module(module)
    return frozenset(importlib.metadata.entry_points().groups) | {kind.group for kind in registry.KINDS}


def spec_of(name: str) -> Any:
    try:
        return importlib.util.find_spec(name)
    except (ImportError, ValueError, AttributeError):
        return None


@cache
def resolves(name: str) -> str | None:
    """None when ``name`` (``a.b.c`` or ``a.b:c``) is a module or an attribute of its longest
    importable prefix, else why not."""
    module_name, _, attribute = name.partition(":")
    parts = module_name.split(".")
    for cut in range(len(parts), 0, -1):
        prefix = ".".join(parts[:cut])
        if spec_of(prefix) is None:
            continue
        try:
            value: Any = importlib.import_module(prefix)
        except Exception as exc:
            return f"module {prefix} does not import ({type(exc).__name__}: {exc})"
        rest = parts[cut:] + ([attribute] if attribute else [])
        for i, part in enumerate(rest):
            if not hasattr(value, part):
                return f"{'.'.join([prefix, *rest[:i]])} has no attribute {part!r}"
            value = getattr(value, part)
        return None
    return "no such module"


def module_names(mention: Mention) -> Iterator[str]:
    if mention.kind == "code":
        for match in MODULE_NAME.finditer(mention.text):
            name = match.group(1)
            if name in entry_point_groups():
                continue
            yield f"{name}:{match.group(2)}" if match.group(2) else name
    if mention.kind in ("code",) or mention.kind.startswith("block:"):
        for match in PYTHON_M.finditer(mention.text):
            yield match.group(1).rstrip(".")
    if mention.kind.split(":", 1)[-1] in PYTHON_LANGUAGES and mention.kind.startswith("block:"):
        for match in PYTHON_IMPORT.finditer(mention.text):
            module = match.group(1) or match.group(3)
            if module.split(".")[0] not in MODULE_ROOTS:
                continue
            yield module
            for imported in (match.group(2) or "").replace("\n", " ").split(","):
                words = imported.split()
                if words:
                    yield f"{module}:{words[0]}"


def module_problems(found: list[Mention]) -> list[str]:
    problems: list[str] = []
    for mention in found:
        for name in module_names(mention):
            why = resolves(name)
            if why is not None:
                problems.append(f"{mention.where}:{mention.line}: module {name}: {why}")
    return problems


# -- commands ----------------------------------------------------------------------------------------


def commands(mention: Mention) -> Iterator[tuple[str, ...]]:
    """``(program, command)`` and, where a second lowercase word follows, ``(program, command, word)``."""
    if mention.kind == "link":
        return
    if mention.kind.startswith("block:") and mention.kind.split(":", 1)[1] not in SHELL_LANGUAGES:
        return
    for match in COMMAND.finditer(mention.text):
        program, command, word = match.groups()
        yield (program, command) if word is None else (program, command, word)


def program(name: str) -> list[str]:
    """How to run a console script of this environment: the script beside the interpreter, on PATH,
    or its module."""
    beside = Path(sys.executable).parent / name
    if beside.is_file():
        return [str(beside)]
    found = shutil.which(name)
    if found:
        return [found]
    return [sys.executable, "-m", {"datagen": "datagen.cli.main", "osvp": "osvp.cli"}[name]]


def run_help(words: tuple[str, ...]) -> tuple[int, str]:
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb"}
    done = subprocess.run(
        [*program(words[0]), *words[1:], "--help"], capture_output=True, text=True, env=env, timeout=120
    )
    return done.returncode, done.stdout + done.stderr


def command_problems(found: list[Mention]) -> list[str]:
    """Run each distinct command's ``--help`` once. ``datagen GROUP SUB --help`` exits 0 only for a real
    SUB of a real GROUP; after a command that is not a group the second word is an argument, and help
    still exits 0. A command named alone is run alone unless a longer form already showed it real."""
    named = [(mention, words) for mention in found for words in commands(mention)]
    longer = sorted({words for _, words in named if len(words) == 3})
    with ThreadPoolExecutor(max_workers=4) as pool:
        answers = dict(zip(longer, pool.map(run_help, longer), strict=True))
        real = {words[:2] for words, (code, _) in answers.items() if code == 0}
        alone = sorted({words for _, words in named if len(words) == 2 and words not in real})
        answers.update(zip(alone, pool.map(run_help, alone), strict=True))
    problems: list[str] = []
    for mention, words in named:
        code, _ = answers.get(words, (0, ""))
        if code != 0:
            problems.append(
                f"{mention.where}:{mention.line}: command `{' '.join(words)}`: --help exits {code}, not a command"
            )
    return problems


# -- the tests ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def found() -> list[Mention]:
    scanned = all_mentions()
    assert any(m.where == "README.md" for m in scanned), "README.md gave no names to check"
    return scanned


def report(problems: list[str]) -> str:
    return "stale names in the docs:\n" + "\n".join(sorted(set(problems)))


def test_every_path_exists(found: list[Mention]) -> None:
    problems = path_problems(found)
    assert not problems, report(problems)


def test_every_module_resolves(found: list[Mention]) -> None:
    problems = module_problems(found)
    assert not problems, report(problems)


def test_every_command_is_a_command(found: list[Mention]) -> None:
    assert any(commands(m) for m in found), "the docs name no datagen or osvp command"
    problems = command_problems(found)
    assert not problems, report(problems)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("See `storage/readers/reader.py` and [the contract](docs/pipeline.md#the-sample-contract).", []),
        ("`storage/samples.py`", ["path storage/samples.py"]),
        ("`datagen/nowhere/`", ["path datagen/nowhere/"]),
        ("[gone](docs/guide/nowhere.md)", ["link to docs/guide/nowhere.md"]),
        ("[gone](SCHEMA.md#no-such-heading)", ["no such heading"]),
        ("`OUT/PROVENANCE.md`, `/tmp/x/y.txt`, `~/.datagen/a.txt`, `s3://b/c.txt`, `../shared/meshes/`", []),
        ("`storage.open_dataset(url)`, `osvp.planning:load_scorer`, `datagen.planners`", []),
        ("`storage.sample_set`", ["module storage.sample_set"]),
        ("`storage.readers.reader.no_such_name`", ["module storage.readers.reader.no_such_name"]),
        ("```python\nfrom storage.stream import ShardStream\nfrom storage import nothing_here\n```", ["nothing_here"]),
        ("`python -m benchmarks.nowhere.script`", ["module benchmarks.nowhere.script"]),
    ],
)
def test_a_stale_name_is_found(text: str, expected: list[str]) -> None:
    """The checker itself on made-up documents: real names pass, each kind of stale one is named."""
    scanned = mentions("README.md", text)
    problems = path_problems(scanned) + module_problems(scanned)
    assert bool(problems) == bool(expected), problems
    for fragment in expected:
        assert any(fragment in problem for problem in problems), problems
    assert all(problem.startswith("README.md:") for problem in problems), problems


def test_commands_are_found_where_written() -> None:
    text = (
        "Run `datagen shards validate URL` or `osvp train --data URL`; not `datagen-reader`, `~/.datagen` "
        "or `-p fixed:match=osvp --x`.\n```bash\ndocker compose exec head datagen status\n```\n"
        "```python\nimport datagen\n```\n"
    )
    named = sorted(words for mention in mentions("README.md", text) for words in commands(mention))
    assert named == [("datagen", "shards", "validate"), ("datagen", "status"), ("osvp", "train")]
