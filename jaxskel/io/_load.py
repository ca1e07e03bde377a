"""Read and write marker recordings: one entry point, one set of conventions.

:func:`load` turns a C3D, TRC, Cortex CSV or jaxskel HDF5 file into a
:class:`~jaxskel.Trial`; :func:`save_trial` writes one back (HDF5, C3D or TRC),
atomically. The format modules (:mod:`jaxskel.io._c3d`, :mod:`jaxskel.io._trc`,
:mod:`jaxskel.io._csv`, :mod:`jaxskel.io._h5`) only parse; everything a user relies
on is decided here, the same way for every format:

* **Units.** Positions are converted to metres. The unit stated by the file is
  used; ``units=`` overrides it; where a file states none, see :func:`resolve_units`.
* **Missing samples.** Empty cells, NaN and samples that are exactly (0, 0, 0)
  are missing (NaN). Vicon and many exporters write zeros for an occluded
  marker; a real marker exactly at the lab origin is vanishingly unlikely.
* **Labels.** Subject prefixes are removed (everything up to the last ``:``,
  e.g. ``"Derrick:LANK"`` -> ``"LANK"``), except where that would make two
  labels equal (two subjects, or OptiTrack rigid bodies ``"ArmL:Marker1"`` and
  ``"SWL:Marker1"``): those keep their full label (``metadata
  ["kept_prefix_labels"]``). Labels that are still repeated get ``_2``,
  ``_3``, ... in file order (``metadata["renamed_labels"]``); blank labels
  become ``point<i>``. HDF5 trials keep their labels as saved.
* **Non-markers.** See :func:`load` (``drop_non_markers``, ``drop_unlabeled``).
* **Vertical axis.** See :func:`infer_up_axis` and :func:`load`.

* **Report.** :func:`jaxskel.io.load_report` says in words what a load dropped,
  renamed or found empty, and why (``jaxskel fit`` and ``jaxskel info`` print it).

Every failure to read is an :class:`~jaxskel.InputError` naming the file and
what is wrong; exceptions of the parsing libraries never escape. Sizes a file
declares (frames, markers, label lengths) are checked against what the file
holds and the memory available before they are allocated
(:mod:`jaxskel.io._bounds`).
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from .._errors import InputError, UnitsWarning
from ._bounds import check_labels
from ._raw import UP_AXES, RawRecording, median_extent, unit_scale
from ._trial import Trial

__all__ = ["load", "save_trial", "infer_up_axis", "median_extent"]

#: Suffix -> format module. Suffixes are compared in lower case.
_READERS = {".c3d": "c3d", ".trc": "trc", ".csv": "csv", ".h5": "h5", ".hdf5": "h5"}

# Vicon's names for trajectories that were reconstructed but never labelled.
_UNLABELED = re.compile(r"^\*\d+$")

# Plug-in-Gait segment axes written as points: a 3-letter segment code (pelvis,
# femur, tibia, foot, toe, head, thorax, clavicle, humerus, radius, hand) plus
# O(rigin)/A(nterior)/L(ateral)/P(roximal). They are model estimates (LFEP is
# the left hip centre), not markers; see pycgm/Movement_trial.c3d.
_PIG_SEGMENT_POINT = re.compile(r"^(PEL|HED|TRX|[LR](FE|TI|FO|TO|CL|HU|RA|HN))[OALP]$")

# The body lives between the floor (h = 0 in lab coordinates) and this height.
_MAX_HEIGHT = 2.5
# Tolerance below the floor: calibration error and markers resting on it.
_BELOW_FLOOR = 0.05
# A marker "touches" the floor when it is this close to it (foot markers sit
# 2-10 cm above the ground; a lying body's markers likewise).
_ON_FLOOR = 0.10


# ---------------------------------------------------------------------- public
def load(
    path: str | os.PathLike[str],
    *,
    drop_unlabeled: bool = False,
    drop_non_markers: bool = True,
    units: str | None = None,
    up_axis: str | None = None,
) -> Trial:
    """Read a marker recording into a :class:`~jaxskel.Trial` (metres, NaN = missing).

    The format follows the suffix: ``.c3d`` (via ezc3d), ``.trc`` (OpenSim),
    ``.csv`` (Cortex/MAC3D export: ``key,value`` header lines, a blank line,
    then name, unit and axis rows and ``time, X, Y, Z, ...`` data rows) and
    ``.h5``/``.hdf5`` (a trial written by :func:`save_trial`).

    Parameters
    ----------
    path
        The file.
    drop_unlabeled
        Drop Vicon's unlabelled trajectories (labels ``*0``, ``*1``, ...).
        They are kept by default: for raw recordings they *are* the data.
    drop_non_markers
        Drop points that are computed, not measured: C3D points listed in
        ``POINT:MODELED_MARKERS`` and Plug-in-Gait segment-axis points
        (``LFEO``, ``LFEA``, ``LFEL``, ``LFEP``, ``PELO``, ...: joint-centre
        estimates, useful as reference but not markers). Points that are not
        positions at all (those listed in ``POINT:ANGLES``, ``FORCES``,
        ``MOMENTS``, ``POWERS``, ``REACTIONS``, ``SCALARS`` or another
        ``POINT:TYPE_GROUPS`` group) are always dropped, since a trial holds
        positions.
    units
        The length unit of the file's values (``"mm"``, ``"cm"``, ``"m"``, ...),
        overriding what the file states. Use it for files without (or with
        wrong) units. Not allowed for HDF5 trials, which are always metres.
    up_axis
        The vertical axis (one of ``"x", "y", "z", "-x", "-y", "-z",
        "unknown"``), overriding the file and the inference.

    Returns
    -------
    Trial
        ``metadata`` holds: ``reader``, ``original_units``, ``units_source``
        (``"file"``, ``"argument"``, ``"assumed"``), ``first_frame`` (1-based
        frame number of the first sample in the original recording),
        ``n_dropped``, ``dropped_labels`` and ``dropped_reasons`` (label ->
        reason), ``label_prefixes`` (subject prefixes found),
        ``kept_prefix_labels`` and ``renamed_labels`` (see the module notes),
        ``empty_labels`` (label -> why: markers kept without a single sample,
        which the fit's cleaning drops), ``short_rows`` (TRC and CSV: data rows
        that end before the last marker's columns), ``up_axis_source`` (``"argument"``, ``"file"``, ``"file+data"``,
        ``"data"``) and ``up_axis_scores``, plus format-specific entries
        (``manufacturer``, ``stated_up_axis``, ...), and ``file``: the path this
        load read (outputs are never written over it). A trial read from HDF5
        gets back the source and metadata it was saved with (``file`` is never
        stored: each load sets its own).

    Notes
    -----
    The vertical axis is decided, first match wins: the ``up_axis`` argument;
    an axis written by jaxskel itself (HDF5 attribute, C3D ``JAXSKEL:UP_AXIS``);
    the axis *letter* a C3D states in ``POINT:Y_SCREEN`` with the *sign* taken
    from the data (writers disagree on the sign: Qualisys writes ``-Z`` for
    Z-up data, and rotated files keep the original statement); otherwise
    (TRC, CSV, C3D without ``Y_SCREEN``) :func:`infer_up_axis` on the data.

    Raises
    ------
    InputError
        Unknown suffix, missing, empty, truncated or corrupt file, a file that
        holds no markers, or invalid arguments. The message names the file.
    """
    file = Path(path)
    fmt = _READERS.get(file.suffix.lower())
    if fmt is None:
        raise InputError(
            f"cannot read {file}: unknown file type {file.suffix!r}; "
            f"supported: {', '.join(sorted(_READERS))}"
        )
    if not file.exists():
        raise InputError(f"cannot read {file}: no such file")
    if not file.is_file():
        raise InputError(f"cannot read {file}: not a regular file")
    if file.stat().st_size == 0:
        raise InputError(f"cannot read {file}: the file is empty")
    check_load_arguments(units, up_axis)  # early, with a helpful message

    raw = _read_raw(fmt, file, units)
    if raw.units.note is not None:
        warnings.warn(raw.units.note, UnitsWarning, stacklevel=2)
    return _to_trial(raw, file, fmt, drop_unlabeled, drop_non_markers, up_axis)


def check_load_arguments(units: str | None, up_axis: str | None) -> None:
    """InputError for a ``units`` or ``up_axis`` that :func:`load` would refuse (for
    callers that load later, as :func:`jaxskel.fit_batch` does)."""
    if units is not None:
        unit_scale(units, Path())
    if up_axis is not None and up_axis not in UP_AXES:
        raise InputError(f"up_axis must be one of {', '.join(UP_AXES)} (--up-axis on the command line); got {up_axis!r}")


def save_trial(trial: Trial, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
    """Write ``trial`` to ``.h5``/``.hdf5``, ``.c3d`` or ``.trc`` (by suffix), atomically.

    HDF5 keeps everything (positions in float64, labels, rate, up axis,
    source, metadata). C3D stores float32 positions in millimetres, the labels,
    rate and first frame, and the up axis (``POINT:X_SCREEN``/``Y_SCREEN`` and
    ``JAXSKEL:UP_AXIS``). TRC stores millimetres with 6 decimals (1 nm) and the
    first frame; the up axis is not part of the format and is inferred again
    on reading.

    Returns the path written. Raises :class:`~jaxskel.InputError` for an
    unknown suffix or an existing file (unless ``overwrite=True``); a failed
    write leaves no file behind and an existing file untouched.
    """
    if not isinstance(trial, Trial):
        raise InputError(f"save_trial needs a Trial, got {type(trial).__name__}")
    file = Path(path)
    trial.save(file, overwrite=overwrite)
    return file


def infer_up_axis(
    positions: Float[np.ndarray, "frames markers 3"],
    candidates: Sequence[str] = ("y", "z", "-y", "-z"),
) -> tuple[str, dict[str, float]]:
    """The vertical axis of a recording in lab coordinates (metres), from its data.

    Lab coordinate systems put the origin on the floor and one axis vertical.
    For each candidate up direction ``u`` with heights ``h = u . x`` three
    cues are scored in [0, 1]:

    * ``A``, above the floor: fraction of present samples with
      ``-0.05 <= h <= 2.5`` m. The body is above the floor and below 2.5 m;
      a horizontal axis through the capture volume has samples on both sides
      of 0, and the wrong sign of the right axis has almost none.
    * ``F``, floor contact: fraction of frames (with >= 3 markers) whose third
      lowest marker is within ``[-0.05, 0.10]`` m, i.e. a foot (heel, toe,
      metatarsal) or a lying body rests on the plane ``h = 0``.
    * ``S``, long axis: the median over frames of the RMS distance of the
      markers from their centroid along the axis, over the largest such value
      among the candidates. An upright body is tallest along the vertical.

    The score is ``2 A + F + S``; ``A`` counts twice because it alone also
    fixes the sign. ``F`` decides for lying or rolling subjects (where ``S``
    favours a horizontal axis), ``S`` for recordings without foot markers.

    ``x`` is not a candidate by default: no common capture system (Vicon,
    Qualisys, OptiTrack, Motion Analysis, OpenSim) uses a vertical X, and
    ruling it out avoids confusing a forward-leaning or lying body's long
    axis with the vertical. It is a heuristic (checked on real recordings:
    docs/bench/evidence_from_docstrings.md): where it matters, pass the axis
    (``load(..., up_axis=)``); :func:`load` keeps the scores in
    ``metadata["up_axis_scores"]``.

    Returns
    -------
    (axis, scores)
        ``axis`` is the best candidate, or ``"unknown"`` when no frame has two
        present markers; ``scores`` maps each candidate to its score.
    """
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise InputError(f"positions must have shape (frames, markers, 3); got {x.shape}")
    for cand in candidates:
        if cand not in UP_AXES or cand == "unknown":
            raise InputError(f"candidate axes must be among {UP_AXES[:-1]}, got {cand!r}")
    present = ~np.isnan(x).any(axis=-1)
    count = present.sum(axis=1)
    framed = count >= 2
    if not framed.any():
        return "unknown", {}
    xz = np.where(present[..., None], x, 0.0)

    # S: per-frame RMS spread about the centroid, along each coordinate axis.
    xs, ps, cs = xz[framed], present[framed], count[framed][:, None]
    centroid = xs.sum(axis=1) / cs
    dev2 = np.where(ps[..., None], (xs - centroid[:, None, :]) ** 2, 0.0)
    spread = np.median(np.sqrt(dev2.sum(axis=1) / cs), axis=0)
    axes = sorted({"xyz".index(c[-1]) for c in candidates})
    spread_ref = max(float(spread[axes].max()), 1e-12)

    three = count >= 3
    scores: dict[str, float] = {}
    for cand in candidates:
        a = "xyz".index(cand[-1])
        sign = -1.0 if cand.startswith("-") else 1.0
        h = sign * x[..., a]
        hp = h[present]
        above = float(np.mean((hp >= -_BELOW_FLOOR) & (hp <= _MAX_HEIGHT)))
        if three.any():
            third = np.partition(np.where(present, h, np.inf)[three], 2, axis=1)[:, 2]
            floor = float(np.mean((third >= -_BELOW_FLOOR) & (third <= _ON_FLOOR)))
        else:
            floor = 0.0
        scores[cand] = 2.0 * above + floor + float(spread[a]) / spread_ref
    best = max(scores, key=scores.__getitem__)
    return best, scores


# ------------------------------------------------------------ shared helpers
def _read_raw(fmt: str, file: Path, units: str | None) -> RawRecording:
    if fmt == "c3d":
        from ._c3d import read_c3d as read
    elif fmt == "trc":
        from ._trc import read_trc as read
    elif fmt == "csv":
        from ._csv import read_csv as read
    else:
        from ._h5 import read_h5 as read
    return read(file, units=units)


def _strip_prefix(label: str) -> tuple[str, str | None]:
    """``"Subject:LKNE"`` -> ``("LKNE", "Subject")``; the prefix is None if absent."""
    if ":" not in label:
        return label, None
    prefix, _, name = label.rpartition(":")
    return name.strip(), prefix.strip()


def _unique_labels(
    names: Sequence[str], originals: Sequence[str]
) -> tuple[list[str], dict[str, str]]:
    """Make labels unique in file order: the 2nd ``X`` becomes ``X_2``, and so on.

    Blank labels become ``point<i>`` (i = position in the file). Returns the new
    labels and ``{original label: new label}`` for every renamed one (an
    original that is itself repeated is keyed ``"<label> #<i>"``).
    """
    taken = set(names)
    seen: set[str] = set()
    out: list[str] = []
    renamed: dict[str, str] = {}
    for i, (name, original) in enumerate(zip(names, originals, strict=True)):
        new = name if name else f"point{i}"
        if new in seen:
            k = 2
            while f"{new}_{k}" in taken or f"{new}_{k}" in seen:
                k += 1
            new = f"{new}_{k}"
        if new != original:
            key = original if originals.count(original) == 1 else f"{original} #{i}"
            if new != name or not name:
                renamed[key] = new
        seen.add(new)
        out.append(new)
    return out, renamed


def _to_trial(
    raw: RawRecording,
    file: Path,
    fmt: str,
    drop_unlabeled: bool,
    drop_non_markers: bool,
    up_axis: str | None,
) -> Trial:
    n_points = len(raw.labels)
    check_labels(raw.labels, file)
    if raw.positions.shape[1] != n_points:
        raise InputError(
            f"{file}: {raw.positions.shape[1]} point columns but {n_points} labels; "
            "the file is inconsistent"
        )
    names: list[str] = []
    prefixes: set[str] = set()
    for lab in raw.labels:
        lab = lab.strip()
        if raw.strip_prefixes:
            lab, prefix = _strip_prefix(lab)
            if prefix:
                prefixes.add(prefix)
        names.append(lab)

    if n_points == 0:
        raise InputError(f"{file} contains no 3D points; it is not a marker recording")
    reasons: dict[int, str] = {}
    for i, name in enumerate(names):
        if i in raw.non_position:
            reasons[i] = raw.non_marker.get(i, "not a position")
        elif drop_non_markers and i in raw.non_marker:
            reasons[i] = raw.non_marker[i]
        elif drop_non_markers and _PIG_SEGMENT_POINT.match(name):
            reasons[i] = "Plug-in-Gait segment point"
        elif drop_unlabeled and _UNLABELED.match(name):
            reasons[i] = "unlabeled"
    keep = [i for i in range(n_points) if i not in reasons]
    if not keep:
        raise InputError(
            f"{file}: all {n_points} points were dropped as non-markers "
            f"({', '.join(sorted(set(reasons.values())))}); pass drop_non_markers=False "
            "or drop_unlabeled=False to keep them"
        )
    if raw.positions.shape[0] == 0:
        raise InputError(f"{file} contains no frames")

    originals = [raw.labels[i].strip() for i in keep]
    kept_names = [names[i] for i in keep]
    # Stripping must not merge markers: where two subjects (or OptiTrack rigid
    # bodies, "ArmL:Marker1" / "SWL:Marker1") share a name, keep their prefixes.
    # (Only where the prefixes differ: a label repeated verbatim gets a suffix below.)
    variants: dict[str, set[str]] = {}
    for n, o in zip(kept_names, originals, strict=True):
        variants.setdefault(n, set()).add(o)
    ambiguous = {n for n, found in variants.items() if len(found) > 1}
    kept_prefix = [
        o for n, o in zip(kept_names, originals, strict=True) if n in ambiguous and n != o
    ]
    kept_names = [o if n in ambiguous else n for n, o in zip(kept_names, originals, strict=True)]
    labels, renamed = _unique_labels(kept_names, originals)
    positions = raw.positions[:, keep]

    # Markers kept without a single sample: the fit's cleaning drops them, so say why now.
    never = ~(~np.isnan(positions).any(axis=-1)).any(axis=0)
    empty = {
        label: raw.empty_reasons.get(i, "missing or at 0, 0, 0 in every frame")
        for label, i, gone in zip(labels, keep, never, strict=True) if gone
    }
    dropped = [raw.labels[i].strip() for i in sorted(reasons)]
    dropped_reasons = {raw.labels[i].strip(): reasons[i] for i in sorted(reasons)}
    axis, up_source, scores = _resolve_up_axis(positions, raw, up_axis)
    metadata: dict[str, Any] = {
        "reader": fmt,
        "original_units": raw.units.name,
        "units_source": raw.units.source,
        "first_frame": int(raw.first_frame),
        "n_dropped": len(dropped),
        "dropped_labels": dropped,
        "dropped_reasons": dropped_reasons,
        "label_prefixes": sorted(prefixes),
        "kept_prefix_labels": kept_prefix,
        "renamed_labels": renamed,
        "empty_labels": empty,
        "up_axis_source": up_source,
        "up_axis_scores": {k: round(v, 4) for k, v in scores.items()},
        **raw.extra,
    }
    if raw.provenance is not None:
        # A saved trial keeps the provenance it was saved with; this load only
        # adds what it changed (dropped points, an explicit up axis).
        metadata = dict(raw.provenance)
        if dropped:
            metadata["dropped_labels"] = [*metadata.get("dropped_labels", []), *dropped]
            metadata["dropped_reasons"] = {**metadata.get("dropped_reasons", {}), **dropped_reasons}
            metadata["n_dropped"] = len(metadata["dropped_labels"])
        if up_source == "argument":
            metadata["up_axis_source"] = up_source
    metadata["file"] = str(file)  # the file this load read (a saved trial keeps its own source)
    return Trial(
        positions=positions,
        labels=tuple(labels),
        rate=raw.rate,
        up_axis=axis,
        source=str(file) if raw.source is None else raw.source,
        metadata=metadata,
    )


def _resolve_up_axis(
    positions: np.ndarray, raw: RawRecording, override: str | None
) -> tuple[str, str, dict[str, float]]:
    """(axis, how it was decided, inference scores); the rule is in :func:`load`."""
    if override is not None:
        return override, "argument", {}
    if raw.declared_up_axis is not None:
        return raw.declared_up_axis, "file", {}
    if raw.stated_up_letter is not None:
        letter = raw.stated_up_letter
        axis, scores = infer_up_axis(positions, candidates=(letter, "-" + letter))
        return axis, "file+data", scores
    axis, scores = infer_up_axis(positions)
    return axis, "data", scores
