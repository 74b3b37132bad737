"""Export of computed fields to VTU (meshio), to open in ParaView.

* :func:`write_fields_vtu`: one mesh with any number of nodal fields (name -> (N,) values);
* :func:`write_field_series`: fields at several times, one VTU per time and a ``.pvd``
  collection that ParaView opens as a time series;
* :func:`write_paper_fields`: the reproduction's fields (end of braking, sensor maximum).

Cells are written as VTK hexahedra (8 nodes) or quadratic hexahedra (20 nodes), the mesh's
own node order; point data are float64, in the units their names say.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import ArrayLike

from fleetbrake.model.thermal import Mesh

if TYPE_CHECKING:
    from fleetbrake.paper.results import PaperReproduction

__all__ = ["write_field_series", "write_fields_vtu", "write_paper_fields"]


def write_fields_vtu(
    mesh: Mesh, path: str | Path, fields: Mapping[str, ArrayLike] | None = None
) -> Path:
    """Write ``mesh`` and its nodal ``fields`` (each (N,) or (N, k)) as a VTU file."""
    path = Path(path)
    if path.suffix != ".vtu":
        raise ValueError(f"a VTU file name ends in .vtu, got {path.name!r}")
    data: dict[str, np.ndarray] = {}
    for name, values in (fields or {}).items():
        array = np.asarray(values, dtype=np.float64)
        if array.shape[0] != mesh.n_nodes:
            raise ValueError(
                f"field {name!r} has {array.shape[0]} values, the mesh {mesh.n_nodes} nodes"
            )
        data[name] = array
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.write_vtu(str(path), data)
    return path


def write_field_series(
    mesh: Mesh,
    directory: str | Path,
    fields_c: ArrayLike,
    times_s: Sequence[float],
    *,
    name: str = "temperature_c",
    stem: str = "field",
) -> Path:
    """Write ``fields_c`` (K, N) at ``times_s`` (K) as ``stem_0000.vtu``... and ``stem.pvd``.

    Returns the ``.pvd`` path (open that in ParaView for the time series).
    """
    directory = Path(directory)
    fields = np.asarray(fields_c, dtype=np.float64)
    if fields.ndim != 2 or fields.shape[0] != len(times_s):
        raise ValueError(f"fields_c must be (len(times_s), N), got {fields.shape}")
    entries = []
    for k, (t, field) in enumerate(zip(times_s, fields, strict=True)):
        vtu = write_fields_vtu(mesh, directory / f"{stem}_{k:04d}.vtu", {name: field})
        entries.append(
            f'    <DataSet timestep="{float(t):.9g}" part="0" file={quoteattr(vtu.name)}/>'
        )
    pvd = directory / f"{stem}.pvd"
    pvd.write_text(
        '<?xml version="1.0"?>\n'
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        "  <Collection>\n" + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n"
    )
    return pvd


def write_paper_fields(rep: PaperReproduction, directory: str | Path) -> list[Path]:
    """One VTU per manoeuvre, ``paper_<name>_fields.vtu``, with the fields
    ``temperature_end_of_braking_c`` and ``temperature_at_sensor_peak_c``."""
    paths = []
    mesh = rep.model.mesh
    for name, run in rep.runs.items():
        fields = {}
        if run.field_end_c is not None:
            fields["temperature_end_of_braking_c"] = run.field_end_c
        if run.field_peak_c is not None:
            fields["temperature_at_sensor_peak_c"] = run.field_peak_c
        paths.append(write_fields_vtu(mesh, Path(directory) / f"paper_{name}_fields.vtu", fields))
    return paths
