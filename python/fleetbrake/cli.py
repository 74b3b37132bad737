"""The ``fleetbrake`` command line (contract: ``shared/spec/interface.md``).

Each command is a thin shell: it parses arguments, calls one function of the package, and
turns expected failures into a clear message and a non-zero exit code.
"""

from __future__ import annotations

import typer

app = typer.Typer(
    name="fleetbrake",
    help="Thermal watch over the cast-iron brake blocks of a freight-wagon fleet.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks that print their figures (last line: one JSON object).")
app.add_typer(bench_app, name="bench")


def main() -> None:
    """Entry point of the ``fleetbrake`` script."""
    app()


if __name__ == "__main__":
    main()
