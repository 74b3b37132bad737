"""The demo's output directory: it holds only one demo's results.

An existing directory is refused unless ``force``, which wipes it first, and only if it is
empty or was made by a demo (it holds the marker file :data:`MARKER`), so that results are
never mixed and nothing else is ever deleted.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from fleetbrake.app.demo.config import DemoError, DemoExistsError

__all__ = ["MARKER", "prepare_out_dir"]

MARKER = ".fleetbrake-demo"
"""File written first into the output directory: ``force`` wipes only a directory holding
it (or an empty one)."""


def prepare_out_dir(out_dir: str | Path, *, force: bool = False) -> Path:
    """Make ``out_dir`` ready for a demo: created if missing; an empty one is used as it is;
    one holding anything is refused (:class:`DemoExistsError`) unless ``force``, and then
    wiped only if it holds the demo marker. Writes the marker."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DemoError(f"{out}: exists and is not a directory; give another --out")
    if out.is_dir() and any(out.iterdir()):
        marked = (out / MARKER).is_file()
        if not force and marked:
            raise DemoExistsError(
                f"{out}: already holds the results of an earlier demo, and results are never "
                "mixed: give --force to wipe it and run again, or another --out"
            )
        if not force:
            raise DemoExistsError(
                f"{out}: already holds files that are not a demo's; give an empty or new "
                "directory as --out"
            )
        if not marked:
            raise DemoExistsError(
                f"{out}: holds files but no {MARKER} marker, so it was not made by "
                "`fleetbrake demo`; --force wipes only a demo's directory: give an empty or "
                "new directory as --out"
            )
        resolved = out.resolve()
        if resolved == Path.cwd().resolve() or resolved in Path.cwd().resolve().parents:
            raise DemoError(f"{out}: is the current directory or holds it; not wiping it")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text(
        "Made by `fleetbrake demo`; `fleetbrake demo --force` may wipe this directory.\n",
        encoding="utf-8",
    )
    return out
