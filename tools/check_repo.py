"""Repository checks that ruff, mypy and import-linter do not make (run by ``make lint``).

Sizes:
  * no module in ``python/fleetbrake`` over 800 lines, no function or method there over 150
    lines (from ``def`` to its last line);
  * no file in ``crates/`` over 1,500 lines.

Words, in docs/, README.md, python/, tests/, crates/, Makefile and pyproject.toml (binary
files skipped): names of work periods, internal tags (three letters and a number, such as
the estimator's or the close loop's), references to issue numbers and scratch paths under
the temporary directory. The documentation and the code describe the present system; its
history belongs in git and in ``docs/decisions/``.

Usage: ``python tools/check_repo.py [ROOT]`` (ROOT: the repository, by default the parent of
this file's directory). Prints one line per finding, ``path:line: what``, and exits 1 when
there is any.
"""

from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 150
MAX_CRATE_FILE_LINES = 1500

PACKAGE = Path("python/fleetbrake")
CRATES = Path("crates")
WORD_ROOTS = ("docs", "README.md", "python", "tests", "crates", "Makefile", "pyproject.toml")
"""What the word search reads (directories searched whole)."""

SKIPPED_DIRS = {"__pycache__", "target", "node_modules", ".git"}
THIS_FILE = Path("tools/check_repo.py")

# Each pattern is assembled from pieces so that this file's own text does not match it.
WORD_PATTERNS: tuple[tuple[str, re.Pattern[str]], ...] = (
    ("work-period name", re.compile(r"\b" + "ses" + r"sions?\s+#?\d+\b", re.IGNORECASE)),
    ("work-period name", re.compile(r"\b" + "sit" + r"tings?\b", re.IGNORECASE)),
    ("internal tag", re.compile(r"\b(?:EST|CL|RUN|FL|EV|ING|SIM)" + r"[0-9]+\b")),
    ("issue reference", re.compile(r"\b" + "iss" + r"ues?\s+#?\d+\b", re.IGNORECASE)),
    ("scratch path", re.compile("/" + "tmp" + "/")),
)


@dataclass(frozen=True, order=True)
class Finding:
    """One violation: where, and what (with the figure and the limit, or the word)."""

    path: str
    line: int
    what: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.what}"


def _files(root: Path, top: Path) -> Iterator[Path]:
    """The files under ``root / top`` (``top`` itself when it is a file), in a stable order."""
    start = root / top
    if start.is_file():
        yield start
        return
    if not start.is_dir():
        return
    for path in sorted(start.rglob("*")):
        relative = path.relative_to(root).parts
        if any(part in SKIPPED_DIRS or part.startswith(".") for part in relative[:-1]):
            continue
        if path.is_file():
            yield path


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary file (a NUL byte, or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def _name(root: Path, path: Path) -> str:
    return path.relative_to(root).as_posix()


def size_findings(root: Path) -> list[Finding]:
    """Modules, functions and crate files over their limits."""
    found: list[Finding] = []
    for path in _files(root, PACKAGE):
        if path.suffix != ".py":
            continue
        text = path.read_text(encoding="utf-8")
        lines = len(text.splitlines())
        name = _name(root, path)
        if lines > MAX_MODULE_LINES:
            found.append(Finding(name, 1, f"module of {lines} lines (limit {MAX_MODULE_LINES})"))
        try:
            tree = ast.parse(text, filename=name)
        except SyntaxError as error:
            found.append(Finding(name, error.lineno or 1, f"not Python: {error.msg}"))
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(
                        Finding(
                            name,
                            node.lineno,
                            f"function {node.name} of {length} lines (limit {MAX_FUNCTION_LINES})",
                        )
                    )
    for path in _files(root, CRATES):
        content = _text(path)
        if content is None:
            continue
        lines = len(content.splitlines())
        if lines > MAX_CRATE_FILE_LINES:
            found.append(
                Finding(
                    _name(root, path),
                    1,
                    f"file of {lines} lines (limit {MAX_CRATE_FILE_LINES})",
                )
            )
    return found


def word_findings(root: Path) -> list[Finding]:
    """Work-period names, internal tags, issue references and scratch paths."""
    found: list[Finding] = []
    for top in WORD_ROOTS:
        for path in _files(root, Path(top)):
            if path.relative_to(root) == THIS_FILE:
                continue
            text = _text(path)
            if text is None:
                continue
            for number, line in enumerate(text.splitlines(), start=1):
                for what, pattern in WORD_PATTERNS:
                    match = pattern.search(line)
                    if match is not None:
                        found.append(Finding(_name(root, path), number, f"{what}: {match[0]!r}"))
    return found


def main(argv: list[str]) -> int:
    root = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parent.parent
    findings = sorted(size_findings(root) + word_findings(root))
    for finding in findings:
        print(finding)
    if findings:
        print(f"check_repo: {len(findings)} findings", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
