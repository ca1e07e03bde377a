"""OpenSim storage files (``.sto``, ``.mot``): joint angles out, any storage table in.

The format is OpenSim's tab-separated table (``STOFileAdapter``, version 1)::

    <name>
    version=1
    nRows=F
    nColumns=C+1
    inDegrees=yes
    endheader
    time<TAB>label_1<TAB>...
    0.00000000<TAB>12.3456789<TAB>...

:func:`write_angles_sto` writes a :class:`jaxskel.anatomy.JointAngles` in degrees
(``inDegrees=yes``), one column per angle (``knee_l_flexion``, ...), atomically.
:func:`read_sto` reads such a table back (any header keys, ``inDegrees`` yes or no) as a
:class:`StoTable`; values stay in the file's units.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._errors import InputError
from ..io import atomic_output, check_output

if TYPE_CHECKING:
    from ..anatomy import JointAngles

__all__ = ["StoTable", "read_sto", "write_angles_sto"]


@dataclasses.dataclass(frozen=True)
class StoTable:
    """One OpenSim storage table.

    Attributes
    ----------
    name
        The table's name (the file's first line).
    labels
        (C,) column labels, the ``time`` column left out.
    time
        (F,) seconds.
    values
        (F, C) as written in the file (degrees where :attr:`in_degrees`).
    in_degrees
        The header's ``inDegrees`` (``False`` when absent).
    header
        Every ``key=value`` line of the header.
    """

    name: str
    labels: tuple[str, ...]
    time: np.ndarray
    values: np.ndarray
    in_degrees: bool
    header: dict[str, str]

    def column(self, label: str) -> np.ndarray:
        """(F,) the column ``label``."""
        if label not in self.labels:
            raise InputError(f"no column {label!r}; columns: {', '.join(self.labels)}")
        return self.values[:, self.labels.index(label)]


def write_angles_sto(angles: JointAngles, path: str | os.PathLike[str], *, overwrite: bool = False,
                     name: str = "jaxskel joint angles") -> Path:
    """Write ``angles`` as an OpenSim ``.sto`` table in degrees, atomically; returns the path.

    An existing file is replaced only with ``overwrite``."""
    path = check_output(path, "sto")
    values = angles.degrees
    lines = [name, "version=1", f"nRows={values.shape[0]}", f"nColumns={values.shape[1] + 1}", "inDegrees=yes",
             "endheader", "\t".join(("time", *angles.names))]
    table = np.column_stack([angles.time, values])
    body = "\n".join("\t".join(f"{v:.8f}" for v in row) for row in table)
    with atomic_output(path, overwrite=overwrite) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n" + body + ("\n" if body else ""), encoding="ascii")
    return path


def read_sto(path: str | os.PathLike[str]) -> StoTable:
    """Read an OpenSim storage table (``.sto``/``.mot``, version 1). Raises :class:`InputError`
    when the file has no ``endheader`` line, no ``time`` column, or rows of the wrong width."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    try:
        end = next(i for i, line in enumerate(lines) if line.strip().lower() == "endheader")
    except StopIteration:
        raise InputError(f"{path}: not an OpenSim storage file (no 'endheader' line)") from None
    header = dict(line.split("=", 1) for line in lines[1:end] if "=" in line)
    labels = lines[end + 1].split("\t") if end + 1 < len(lines) else []
    if not labels or labels[0].strip().lower() != "time":
        raise InputError(f"{path}: the first column after 'endheader' must be 'time', got {labels[:1]}")
    rows = [line.split("\t") for line in lines[end + 2:] if line.strip()]
    bad = next((i for i, r in enumerate(rows) if len(r) != len(labels)), None)
    if bad is not None:
        raise InputError(f"{path}: data row {bad + 1} has {len(rows[bad])} values for {len(labels)} columns")
    data = np.asarray(rows, float).reshape(len(rows), len(labels))
    return StoTable(name=lines[0].strip(), labels=tuple(s.strip() for s in labels[1:]), time=data[:, 0],
                    values=data[:, 1:], in_degrees=header.get("inDegrees", "no").strip().lower() == "yes",
                    header={k.strip(): v.strip() for k, v in header.items()})
