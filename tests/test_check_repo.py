"""``tools/check_repo.py`` (a ``make lint`` step): it reports modules, functions and crate
files over their limits and the words the docs and code must not hold, one ``path:line``
each, exits 1 on any, and passes a clean tree."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "tools" / "check_repo.py"

# The words the check refuses, assembled so that this file does not hold them itself.
TAG = "EST" + "13"
PERIOD = "ses" + "sion 12"
ISSUE = "iss" + "ue 7"
PERIOD_WORD = "sit" + "ting"
SCRATCH_DIR = "/" + "tmp/"
SCRATCH = SCRATCH_DIR + "scratch.txt"
LOOKALIKE = "T" + TAG
"""An identifier that holds a tag's letters inside a longer word: not a tag."""


def _check(root: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(SCRIPT), str(root)], capture_output=True, text=True, check=False
    )


def _write(root: Path, relative: str, text: str) -> Path:
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def _clean_tree(root: Path) -> None:
    _write(root, "python/fleetbrake/__init__.py", '"""A package."""\n')
    _write(
        root,
        "python/fleetbrake/small.py",
        f"{LOOKALIKE} = 1  # identifiers that hold the letters are not tags: SIMD2, RUNS3\n"
        f"def f() -> int:\n    return {LOOKALIKE}\n",
    )
    _write(root, "crates/core/src/lib.rs", "pub fn f() -> u32 { 1 }\n" * 10)
    _write(root, "docs/guide.md", "# Guide\n\nEach recording session of a wagon is one file.\n")
    _write(root, "README.md", "# fleetbrake\n")
    _write(root, "tests/test_small.py", "def test_f() -> None:\n    assert True\n")
    (root / "docs" / "img").mkdir()
    (root / "docs" / "img" / "plot.png").write_bytes(b"\x89PNG\0\0" + TAG.encode())


def test_a_clean_tree_passes(tmp_path: Path) -> None:
    _clean_tree(tmp_path)
    result = _check(tmp_path)
    assert result.returncode == 0, result.stdout
    assert result.stdout == ""


def test_a_long_module_and_a_long_function_are_reported(tmp_path: Path) -> None:
    _clean_tree(tmp_path)
    _write(tmp_path, "python/fleetbrake/big.py", "x = 1\n" * 801)
    body = "".join(f"        y{i} = {i}\n" for i in range(150))
    _write(
        tmp_path, "python/fleetbrake/long.py", "\n\nclass A:\n    def run(self) -> None:\n" + body
    )
    _write(tmp_path, "crates/core/src/big.rs", "// line\n" * 1501)
    result = _check(tmp_path)
    assert result.returncode == 1
    assert result.stdout.splitlines() == [
        "crates/core/src/big.rs:1: file of 1501 lines (limit 1500)",
        "python/fleetbrake/big.py:1: module of 801 lines (limit 800)",
        "python/fleetbrake/long.py:4: function run of 151 lines (limit 150)",
    ]


@pytest.mark.parametrize(
    ("relative", "line", "what"),
    [
        ("python/fleetbrake/small.py", f"x = 2  # tuned in {TAG}\n", f"internal tag: '{TAG}'"),
        ("tests/test_small.py", f"# measured in {PERIOD}\n", f"work-period name: '{PERIOD}'"),
        ("docs/guide.md", f"As {ISSUE} asks.\n", f"issue reference: '{ISSUE}'"),
        ("crates/core/src/lib.rs", f"// see {SCRATCH}\n", f"scratch path: '{SCRATCH_DIR}'"),
        ("Makefile", f"# one {PERIOD_WORD}\n", f"work-period name: '{PERIOD_WORD}'"),
    ],
)
def test_a_forbidden_word_is_reported_with_its_line(
    tmp_path: Path, relative: str, line: str, what: str
) -> None:
    _clean_tree(tmp_path)
    path = tmp_path / relative
    before = path.read_text(encoding="utf-8") if path.exists() else ""
    _write(tmp_path, relative, before + line)
    result = _check(tmp_path)
    assert result.returncode == 1
    number = len(before.splitlines()) + 1
    assert result.stdout.splitlines() == [f"{relative}:{number}: {what}"]


def test_the_check_does_not_report_itself() -> None:
    result = _check(ROOT)
    assert "tools/check_repo.py" not in result.stdout
    assert "tests/test_check_repo.py" not in result.stdout
