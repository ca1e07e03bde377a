"""The rigid skeleton in a result file: ``/skeleton``, written and read back exactly.

:func:`write_skeleton` stores every field of a :class:`jaxskel.skeleton.Skeleton` in the
``/skeleton`` group (float64 arrays as they are, so a round trip is bit-exact; its
``diagnostics`` go to ``/diagnostics@rigid`` as JSON, as they always have).
:func:`load_skeleton` reads them back from any result file that holds a skeleton: a fit's
(``jaxskel fit``, ``fit_batch``) or a tracked trial's (``jaxskel track``), whose
``/skeleton`` is its calibration's, unchanged. Files written before ``/skeleton`` held the
tree, the labels and the names get them from ``/topology``, ``/markers`` and ``/segments``.

The contract: ``load_skeleton(path)`` after ``SkeletonResult.save(path)`` returns a skeleton
whose arrays equal the fitted one's bit for bit, so that
:func:`jaxskel.skeleton.inverse_kinematics` on it gives the same motion.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .._errors import InputError, SchemaError
from ..io import put

__all__ = ["load_skeleton", "read_skeleton", "write_skeleton"]

#: The arrays of a Skeleton stored under their own names in ``/skeleton``.
_ARRAYS = ("edges", "marker_segment", "marker_offsets", "joint_offsets", "bones", "bone_lengths", "bone_segment",
           "segment_lengths", "marker_rms")


def write_skeleton(group: h5py.Group, skeleton: Any, segment_names: Any = None) -> None:
    """Fill ``group`` (``/skeleton``) with every field of ``skeleton`` but its diagnostics.

    ``segment_names`` overrides the skeleton's own (:meth:`Skeleton.names`)."""
    from ..joints import bone_uncertainty

    for name in _ARRAYS:
        put(group, name, np.asarray(getattr(skeleton, name)))
    group.attrs["n_segments"] = int(skeleton.n_segments)
    put(group, "root", np.int64(skeleton.root))
    put(group, "marker_labels", np.asarray(list(skeleton.marker_labels), dtype=str))
    names = skeleton.names() if segment_names is None else tuple(segment_names)
    put(group, "segment_names", np.asarray(list(names), dtype=str))
    put(group, "bone_uncertainty", bone_uncertainty(skeleton))
    put(group, "nonrigid_markers", np.asarray(list(skeleton.nonrigid_markers), dtype=str))


def _text(values: Any) -> tuple[str, ...]:
    return tuple(v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel().tolist())


def read_skeleton(f: h5py.File, where: str = "result file") -> Any:
    """The :class:`Skeleton` stored in an open result file (module docstring)."""
    from ..skeleton import Skeleton, longest_bones

    if "skeleton" not in f or "marker_offsets" not in f["skeleton"]:
        raise InputError(
            f"{where} holds no rigid skeleton (it was fitted with --no-rigid, or is not a fit's result); "
            "fit again with the rigid skeleton on (the default)"
        )
    g = f["skeleton"]

    def array(name: str, fallback: str | None = None) -> np.ndarray | None:
        if name in g:
            return np.asarray(g[name][()])
        if fallback is not None and fallback in f:
            return np.asarray(f[fallback][()])
        return None

    edges = array("edges", "topology/edges")
    root = array("root", "topology/root")
    labels = g["marker_labels"] if "marker_labels" in g else f["markers/used_labels"]
    segment = array("marker_segment", "markers/used_segment")
    if edges is None or root is None or segment is None:
        raise SchemaError(f"{where}: /skeleton lacks its tree or its markers' segments; the file is incomplete")
    edges = edges.astype(np.int64).reshape(-1, 2)
    n_segments = int(g.attrs.get("n_segments", len(edges) + 1))
    joint_offsets = np.asarray(g["joint_offsets"][()])
    bones = np.asarray(g["bones"][()]).astype(np.int64).reshape(-1, 2)
    bone_segment = array("bone_segment")
    if bone_segment is None:  # the segment two joints share
        bone_segment = np.asarray([(set(edges[a].tolist()) & set(edges[b].tolist())).pop() for a, b in bones],
                                  dtype=np.int64)
    segment_lengths = array("segment_lengths")
    if segment_lengths is None:
        segment_lengths = longest_bones(bone_segment, g["bone_lengths"][()], n_segments)
    names = _text(g["segment_names"][()]) if "segment_names" in g else (
        _text(f["segments/names"][()]) if "segments/names" in f else ()
    )
    rigid = f["diagnostics"].attrs.get("rigid") if "diagnostics" in f else None
    diagnostics = json.loads(rigid) if rigid is not None else {}
    marker_rms = array("marker_rms")
    return Skeleton(
        n_segments=n_segments,
        edges=edges,
        root=int(root),
        marker_labels=_text(labels[()]),
        marker_segment=segment.astype(np.int64),
        marker_offsets=np.asarray(g["marker_offsets"][()]),
        joint_offsets=joint_offsets,
        bones=bones,
        bone_lengths=np.asarray(g["bone_lengths"][()]),
        bone_segment=bone_segment.astype(np.int64),
        segment_lengths=segment_lengths,
        marker_rms=marker_rms if marker_rms is not None else np.full(len(segment), np.nan),
        nonrigid_markers=_text(g["nonrigid_markers"][()]) if "nonrigid_markers" in g else (),
        diagnostics=diagnostics,
        segment_names=names,
    )


def load_skeleton(path: str | os.PathLike[str]) -> Any:
    """The :class:`jaxskel.skeleton.Skeleton` a result file holds: what was fitted, exactly.

    ``path`` is a result file of ``jaxskel fit`` / :meth:`SkeletonResult.save` /
    :func:`jaxskel.fit_batch`, or of a tracked trial (``jaxskel track``, whose skeleton is
    its calibration's). Segments, marker offsets and labels, joints, bones, root and segment
    names come back bit for bit, so that tracking a new trial on it
    (:func:`jaxskel.track`, :func:`jaxskel.skeleton.inverse_kinematics`) gives what the
    in-memory skeleton gives.

    Raises :class:`InputError` for a missing file, a file that is not a result file or one
    without a rigid skeleton (fitted with ``--no-rigid``), and :class:`SchemaError` for a
    file of a newer jaxskel.
    """
    from ._format import open_result

    path = Path(path)
    with open_result(path, hint="; give the result file of jaxskel fit (-o FILE.h5)") as f:
        return read_skeleton(f, str(path))
