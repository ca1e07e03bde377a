"""What :func:`jaxskel.fit_batch` writes besides the result files.

* the **summary table** (CSV, one row per trial, :data:`COLUMNS`);
* the **completion record** in each result file (group ``/batch``: the inputs'
  signature, the settings and the summary row), which makes a rerun skip trials
  that are finished with the same inputs and settings;
* **bone lengths by marker labels**, comparable across trials, and the subject
  comparison plot of Kirk et al. (2005, Fig. 5): back length against mean upper-arm
  length, one symbol per subject.

A bone is named by marker labels, since segment numbers differ between trials: the
bone on the segment that carries marker ``S`` between its joint with the segment of
marker ``A`` and its joint with the segment of marker ``B`` is ``(A, S, B)``; e.g.
the back of the synthetic body (``jaxskel.synth.full_body``) is
``("LASI", "C7", "LFHD")`` (pelvis, torso, head) and the left upper arm
``("C7", "LUPA", "LFRM")``. A spec may list several triples, whose lengths are
averaged (the paper's "mean upper arm length").
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import InputError
from ..io import atomic_output, check_output, image_format
from ..segment import names_from_markers

__all__ = [
    "COLUMNS",
    "BoneSpec",
    "parse_bone_spec",
    "bone_length",
    "named_bones",
    "summary_row",
    "write_summary",
    "read_summary",
    "completion_record",
    "finished_row",
    "plot_bone_lengths",
]

#: Fixed columns of the summary table; ``bone:<name>`` columns follow for the
#: requested bone specs, then ``bones`` (every bone, JSON, by marker labels).
COLUMNS = (
    "name", "subject", "status", "error", "inputs", "output", "frames", "rate", "markers",
    "segments", "joints", "root", "joints_converged", "undetermined", "joint_cost_median_mm2",
    "ik_rms_median_mm", "seconds",
)
#: Bumped when the completion record changes meaning (older records are refitted).
RECORD_VERSION = 1

BoneSpec = Sequence[tuple[str, str, str]]


# ------------------------------------------------------------------------ bones
def parse_bone_spec(text: str) -> tuple[str, tuple[tuple[str, str, str], ...]]:
    """``"NAME=A,S,B[;A,S,B...]"`` -> ``(name, triples)`` (the CLI's ``--bone``)."""
    name, sep, rest = text.partition("=")
    triples = [tuple(v.strip() for v in part.split(",")) for part in rest.split(";")] if sep else []
    if not (name.strip() and triples and all(len(t) == 3 and all(t) for t in triples)):
        raise InputError(
            f"bad bone spec {text!r}: write NAME=A,S,B (markers on the neighbour, on the bone's segment, "
            "on the other neighbour); several triples separated by ';' are averaged"
        )
    return name.strip(), tuple(triples)  # type: ignore[return-value]


def _normalise_specs(bones: Mapping[str, Any] | None) -> dict[str, tuple[tuple[str, str, str], ...]]:
    out: dict[str, tuple[tuple[str, str, str], ...]] = {}
    for name, spec in (bones or {}).items():
        if isinstance(spec, str):
            out[str(name)] = parse_bone_spec(f"{name}={spec}")[1]
            continue
        triples = [spec] if len(spec) == 3 and all(isinstance(v, str) for v in spec) else list(spec)
        if not triples or not all(len(t) == 3 and all(isinstance(v, str) for v in t) for t in triples):
            raise InputError(
                f"bone {name!r}: give a marker-label triple (A, S, B) or a list of them, got {spec!r}"
            )
        out[str(name)] = tuple(tuple(t) for t in triples)  # type: ignore[misc]
    return out


class _Skeletal:
    """The few arrays bone lengths need, from a SkeletonResult or a result file."""

    def __init__(self, labels, marker_segment, edges, bones, bone_lengths, joint_positions, names=None):
        self.segment_of = {str(lab): int(s) for lab, s in zip(labels, marker_segment) if int(s) >= 0}
        self.edges = np.asarray(edges, dtype=int).reshape(-1, 2)
        self.bones = None if bones is None else np.asarray(bones, dtype=int).reshape(-1, 2)
        self.bone_lengths = None if bone_lengths is None else np.asarray(bone_lengths, dtype=float)
        self.joint_positions = joint_positions
        self.labels = [str(v) for v in labels]
        self.marker_segment = np.asarray(marker_segment, dtype=int)
        n_seg = len(self.edges) + 1
        if names is None or len(names) != n_seg:  # a file without /segments/names
            names = names_from_markers(self.labels, self.marker_segment, n_seg)
        self.names = [str(v) for v in names]

    @classmethod
    def of(cls, result: Any) -> _Skeletal:
        if hasattr(result, "segmentation"):  # SkeletonResult
            sk = result.skeleton
            return cls(
                result.segmentation.labels, result.segmentation.marker_segment, result.edges,
                None if sk is None else sk.bones, None if sk is None else sk.bone_lengths,
                result.joint_positions, result.segment_names,
            )
        sk = result["skeleton"] if "skeleton" in result else None
        return cls(
            result["markers/used_labels"], result["markers/used_segment"], result["topology/edges"],
            None if sk is None else sk.bones, None if sk is None else sk.bone_lengths,
            result["joints/positions"], result["segments/names"] if "segments/names" in result else None,
        )

    def joint_between(self, a: int, b: int) -> int | None:
        hit = np.flatnonzero(((self.edges[:, 0] == a) & (self.edges[:, 1] == b)) |
                             ((self.edges[:, 0] == b) & (self.edges[:, 1] == a)))
        return int(hit[0]) if hit.size else None

    def length(self, j0: int, j1: int) -> float:
        if self.bones is not None and self.bone_lengths is not None:
            for (u, v), length in zip(self.bones.tolist(), self.bone_lengths):
                if {u, v} == {j0, j1}:
                    return float(length)
        jp = np.asarray(self.joint_positions)
        d = np.linalg.norm(jp[:, j0] - jp[:, j1], axis=-1)
        return float(np.nanmedian(d)) if np.isfinite(d).any() else math.nan

    def segment_key(self, s: int) -> str:
        """A segment's name across trials: the first of its marker labels."""
        return next(lab for lab, g in zip(self.labels, self.marker_segment) if g == s)


def bone_length(result: Any, spec: BoneSpec | tuple[str, str, str]) -> float:
    """Length (m) of a bone named by marker labels; NaN where the skeleton has no such bone.

    ``result`` is a :class:`jaxskel.SkeletonResult` or a result file read with
    :func:`jaxskel.load_result`; ``spec`` a triple ``(A, S, B)`` or a list of triples
    (their mean over those present). See the module docstring.
    """
    sk = _Skeletal.of(result)
    triples = _normalise_specs({"bone": spec})["bone"]
    lengths = []
    for a, s, b in triples:
        try:
            sa, ss, sb = (sk.segment_of[v] for v in (a, s, b))
        except KeyError:
            continue
        j0, j1 = sk.joint_between(ss, sa), sk.joint_between(ss, sb)
        if j0 is None or j1 is None or j0 == j1:
            continue
        value = sk.length(j0, j1)
        if math.isfinite(value):
            lengths.append(value)
    return float(np.mean(lengths)) if lengths else math.nan


def named_bones(result: Any) -> dict[str, float]:
    """Every bone, keyed ``"S:A-B"`` by the first marker label of each segment (metres);
    a segment without markers by its name (``segment_names``, :mod:`jaxskel.segment._names`)."""
    sk = _Skeletal.of(result)
    out: dict[str, float] = {}
    n_seg = len(sk.edges) + 1
    for s in range(n_seg):
        joints = [j for j, (p, c) in enumerate(sk.edges.tolist()) if s in (p, c)]
        if not (sk.marker_segment == s).any():
            continue
        for i in range(len(joints)):
            for k in range(i + 1, len(joints)):
                nbr = []
                for j in (joints[i], joints[k]):
                    other = int(sk.edges[j, 0] if sk.edges[j, 1] == s else sk.edges[j, 1])
                    nbr.append(sk.segment_key(other) if (sk.marker_segment == other).any() else sk.names[other])
                a, b = sorted(nbr)
                value = sk.length(joints[i], joints[k])
                out[f"{sk.segment_key(s)}:{a}-{b}"] = round(value, 6) if math.isfinite(value) else None
    return dict(sorted(out.items()))


# -------------------------------------------------------------------- summary rows
def _median_or_nan(values: Any, scale: float = 1.0) -> float:
    arr = np.asarray(values, dtype=float)
    arr = arr[np.isfinite(arr)]
    return round(float(np.median(arr)) * scale, 4) if arr.size else math.nan


def summary_row(
    result: Any, *, name: str, subject: str, inputs: str, output: str, seconds: float,
    bones: Mapping[str, BoneSpec] | None = None,
) -> dict[str, Any]:
    """The summary-table row of one fitted trial (``status`` "ok")."""
    topo = result.topology
    row: dict[str, Any] = dict.fromkeys(COLUMNS, "")
    row.update(
        name=name, subject=subject, status="ok", inputs=inputs, output=output,
        frames=result.trial.n_frames, rate=result.trial.rate, markers=result.trial.n_markers,
        segments=result.n_segments, joints=len(topo.edges), root=int(topo.root),
        joints_converged=f"{int(np.sum(topo.converged))}/{len(topo.edges)}",
        undetermined=len(result.undetermined_joints()),  # joints fixed only to within > 10 cm
        joint_cost_median_mm2=_median_or_nan(topo.joint_cost, 1e6),
        ik_rms_median_mm=_median_or_nan(result.motion.marker_rms, 1e3) if result.motion is not None else math.nan,
        seconds=round(float(seconds), 2),
    )
    for bone, spec in _normalise_specs(bones).items():
        value = bone_length(result, spec)
        row[f"bone:{bone}"] = round(value, 6) if math.isfinite(value) else math.nan
    row["bones"] = json.dumps(named_bones(result))
    return row


def failed_row(*, name: str, subject: str, inputs: str, output: str, error: str, seconds: float) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(COLUMNS, "")
    row.update(name=name, subject=subject, status="failed", error=error, inputs=inputs, output=output,
               seconds=round(float(seconds), 2))
    return row


def write_summary(path: str | os.PathLike[str], rows: Sequence[Mapping[str, Any]]) -> Path:
    """Write the summary CSV atomically (replacing an older summary)."""
    extra = sorted({k for r in rows for k in r if k.startswith("bone:")})
    fields = [*COLUMNS, *extra, "bones"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()})
    with atomic_output(path, overwrite=True) as tmp:
        Path(tmp).write_text(buf.getvalue(), encoding="utf-8")
    return Path(path)


def read_summary(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Rows of a summary CSV, numbers as floats (empty cells NaN)."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for k, v in row.items():
            if k.startswith("bone:") or k in ("frames", "rate", "markers", "segments", "joints", "root",
                                               "undetermined", "joint_cost_median_mm2", "ik_rms_median_mm",
                                               "seconds"):
                try:
                    row[k] = float(v) if v != "" else math.nan
                except ValueError:
                    pass
    return rows


# ------------------------------------------------------------- completion record
def input_signature(inputs: Sequence[Any]) -> list[Any]:
    """Identify the inputs: path, size and modification time of files; a hash of in-memory trials."""
    out: list[Any] = []
    for item in inputs:
        if isinstance(item, (str, os.PathLike)):
            p = Path(item)
            st = p.stat()
            out.append([str(p.resolve()), st.st_size, st.st_mtime_ns])
        else:
            h = hashlib.sha1()
            h.update(np.ascontiguousarray(item.positions).tobytes())
            h.update("\x00".join(item.labels).encode())
            h.update(repr(float(item.rate)).encode())
            out.append(["trial", h.hexdigest()])
    return out


def signature(inputs: Sequence[Any], options: Mapping[str, Any]) -> str:
    return json.dumps(
        {"version": RECORD_VERSION, "inputs": input_signature(inputs), "options": _jsonable(options)},
        sort_keys=True,
    )


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return repr(obj)


def completion_record(sig: str, row: Mapping[str, Any]) -> Any:
    """``extra_groups`` writer of ``/batch``: written last inside the atomic save."""

    def write(group: Any) -> None:
        group.attrs["signature"] = sig
        group.attrs["row"] = json.dumps(_jsonable({k: v for k, v in row.items()}))
        group.attrs["complete"] = True

    return write


def finished_row(path: Path, sig: str) -> dict[str, Any] | None:
    """The stored row if ``path`` is a complete result of the same inputs and settings, else None.

    Anything else (missing, unreadable or truncated file, no completion record,
    other inputs or settings) means: fit again.
    """
    if not path.is_file():
        return None
    try:
        import h5py

        with h5py.File(path, "r") as f:
            if "schema_version" not in f.attrs or "batch" not in f or "topology" not in f:
                return None
            attrs = f["batch"].attrs
            if not bool(attrs.get("complete", False)) or attrs.get("signature") != sig:
                return None
            return json.loads(attrs["row"])
    except (OSError, KeyError, ValueError, TypeError):
        return None


# ------------------------------------------------------------------------- plot
def plot_bone_lengths(
    table: Any,
    x: str,
    y: str,
    *,
    group: str = "subject",
    ax: Any = None,
    path: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
) -> Any:
    """Subject comparison (Kirk et al. 2005, Fig. 5): one bone length against another.

    Parameters
    ----------
    table
        A :class:`jaxskel.BatchResult`, a summary CSV path, or rows (dicts).
    x, y
        Bone columns: a name given in ``fit_batch(bones=...)`` (``"back"``) or the
        column itself (``"bone:back"``).
    group
        Column whose values get one colour/symbol each (default the subject).
    ax, path
        Draw into ``ax``; write the figure to ``path`` (atomic; its suffix, one of the
        image types matplotlib writes, picks the format; checked before drawing).

    Returns the axes.
    """
    import matplotlib.pyplot as plt

    fmt = None if path is None else image_format(check_output(path, "image"))

    if hasattr(table, "table"):
        rows = table.table()
    elif isinstance(table, (str, os.PathLike)):
        rows = read_summary(table)
    else:
        rows = list(table)
    cols = [c if c.startswith("bone:") else f"bone:{c}" for c in (x, y)]
    for c in cols:
        if not any(c in r for r in rows):
            raise InputError(
                f"no column {c!r} in the summary; name bones with fit_batch(bones={{...}}) or --bone NAME=A,S,B"
            )
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 4.2))
    groups: dict[str, list[tuple[float, float]]] = {}
    for r in rows:
        if r.get("status") not in ("ok", "skipped"):
            continue
        try:
            vx, vy = float(r.get(cols[0], math.nan)), float(r.get(cols[1], math.nan))
        except (TypeError, ValueError):
            continue
        if math.isfinite(vx) and math.isfinite(vy):
            groups.setdefault(str(r.get(group, "")) or "(none)", []).append((vx, vy))
    symbols = "osD^vP*Xh<>"
    for i, (name, pts) in enumerate(sorted(groups.items())):
        arr = np.asarray(pts) * 100.0
        ax.scatter(arr[:, 0], arr[:, 1], marker=symbols[i % len(symbols)], s=36, label=f"{name} ({len(pts)})",
                   alpha=0.85)
    ax.set_xlabel(f"{cols[0][5:]} length [cm]")
    ax.set_ylabel(f"{cols[1][5:]} length [cm]")
    ax.set_title("Reconstructed bone lengths per subject")
    ax.grid(True, alpha=0.3)
    if groups:
        ax.legend(title=group, fontsize="small")
    if path is not None:
        fig = ax.figure
        fig.tight_layout()
        with atomic_output(path, overwrite) as tmp:
            fig.savefig(tmp, dpi=120, format=fmt)
    return ax
