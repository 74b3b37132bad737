"""The reduced models shipped in the package: the default block's at the default mesh and at
the coarser meshes of the close loop's numerical term, so that a fresh install's first ``run``
or ``close-loop`` on a fleet of default wagons builds none.

``python -m fleetbrake.model.romdata`` (``make rom-data``) builds each model of
:func:`shipped_models` afresh and writes it, compressed, as ``rom-<key>.npz`` into the
package's ``fleetbrake/model/data`` (or ``--out DIR``), removing the files of keys no longer
shipped. The key (:func:`fleetbrake.model.rom.cache_key`, also in the file's ``meta``) hashes
every input of the model, so a change of the default block, mesh, sensor seat, nominal
convection or :data:`~fleetbrake.model.rom.ROM_VERSION` names another file: the package then
builds the model on demand until the command is run again, and the test of the shipped data
fails saying so.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from fleetbrake.fleet.registry import WagonConfig
from fleetbrake.model.rom import (
    DEFAULT_REFINEMENT,
    ReducedModel,
    cache_key,
    shipped_name,
    wagon_model_inputs,
)

__all__ = ["DATA_DIR", "SHIPPED_REFINEMENTS", "main", "shipped_models", "write_shipped_models"]

DATA_DIR = Path(__file__).with_name("data")
"""The package's folder of shipped models in the source tree."""

SHIPPED_REFINEMENTS = (DEFAULT_REFINEMENT, DEFAULT_REFINEMENT / 1.5, DEFAULT_REFINEMENT / 2.0)
"""The default mesh, and the coarse meshes the close loop's numerical term refits on by
default (the default mesh divided by each of ``CloseLoopConfig.numerical_grid_ratios``)."""


def shipped_models(
    refinements: Sequence[float] = SHIPPED_REFINEMENTS,
) -> dict[str, tuple[WagonConfig, float]]:
    """The models shipped, by key: a wagon of the registry's defaults (the default block and
    sensor seat) on the mesh of each refinement."""
    wagon = WagonConfig(wagon_id="default")
    return {
        cache_key(*wagon_model_inputs(wagon, refinement)): (wagon, float(refinement))
        for refinement in refinements
    }


def write_shipped_models(
    out_dir: Path = DATA_DIR, refinements: Sequence[float] = SHIPPED_REFINEMENTS
) -> list[Path]:
    """Build each model of :func:`shipped_models` afresh (never from a cache) and write it to
    ``out_dir``; remove the ``rom-*.npz`` there of other keys. The files written."""
    models = shipped_models(refinements)
    written = []
    for key, (wagon, refinement) in models.items():
        rom = ReducedModel.build_keyed(*wagon_model_inputs(wagon, refinement))
        assert rom.meta["cache_key"] == key
        path = out_dir / shipped_name(key)
        rom.save(path, compressed=True)
        written.append(path)
    for stale in sorted(set(out_dir.glob("rom-*.npz")) - set(written)):
        stale.unlink()
    return written


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m fleetbrake.model.romdata",
        description="Build the reduced models the package ships and write them into its data.",
    )
    parser.add_argument("--out", type=Path, default=DATA_DIR, help="folder (default: %(default)s)")
    args = parser.parse_args(argv)
    for path in write_shipped_models(args.out):
        print(f"{path} ({path.stat().st_size / 1024:.1f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
