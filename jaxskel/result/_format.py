"""The HDF5 result file: writing a :class:`SkeletonResult`, reading it back.

Schema version 1 (documented in the README, "Result file"):

* attributes on ``/``: ``schema_version``, ``jaxskel_version``, ``source``,
  ``rate``, ``units`` = "m", ``up_axis``, ``created``;
* ``/markers``: ``labels`` (M,) str as in the input, ``segment`` (M,) int (-1
  dropped), ``physical`` (M,) int (physical-marker index after label merging,
  identity otherwise, -1 dropped), ``used_labels`` (M',) the markers after
  cleaning/merging, ``positions`` (F, M', 3) the cleaned positions (NaN missing);
* ``/segments``: ``names`` (S,) str (readable names from the markers' labels unless given,
  :mod:`jaxskel.segment._names`; a file without them is read with them derived the same way),
  ``sizes`` (S,) int, ``eigenvalues``, ``distance_std``;
  ``split_markers`` (the flagged markers that grew the count, see :mod:`jaxskel.pipeline._split_refit`);
  ``passed_joint_markers`` (n, 3) str (joint marker, lone marker, partner: a joint marker that left its group of
  two for a lone marker, its partner joining a third group; one segment fewer each);
  ``left_out_labels``, ``left_out_reasons`` (markers the motion cannot place, left out of the
  skeleton, and why: :func:`jaxskel.segment.left_out_markers`); ``still_spans`` (n, 2) the
  frame ranges of still trials, which the joint stages leave out;
  attributes ``eigengap_segments``, ``count_rule`` (given / eigengap / rigid / most rigid / split), ``max_segments``,
  ``rigid_limit`` (metres), ``sigma``, ``white_noise`` (metres), ``split_from`` (the automatic count before it grew, 0 if it did not),
  ``rigid_count`` (the first larger count with every group rigid, passed over for a lone marker; 0 if none);
* ``/topology``: ``joint_cost`` (S, S) the MST weight (inf = infeasible; attribute
  ``joint_cost_weight`` says which, see :class:`jaxskel.joints.PairCosts`), ``joint_objective``
  (S, S) Kirk's Q, ``edges`` (J, 2) parent -> child, ``root`` (), ``roots`` (component roots), ``infeasible``
  (n, 2) pairs with ``infeasible_reason`` (n,) str, ``untested``/``untested_std``, ``near_ties`` (t, 3)
  (joint, rival pair) with ``near_ties_margin`` (t, 2) (margin, noise allowance); ``fixed_misfit``
  (S, S), ``pose_exchanges`` (x, 4) (removed pair, added pair) with ``pose_exchanges_values`` (x, 4)
  (misfit removed, added; joint cost removed, added) and ``pose_exchanges_test`` (x,) str (``fixed`` or
  ``sphere``, :class:`jaxskel.joints.PoseExchange`), ``attachments`` (a, 3) (one-marker segment, host, bridge or -1)
  with ``attachments_rigidity`` (a,) metres (:class:`jaxskel.joints.Attachment`);
* ``/joints``: ``positions`` (F, J, 3) (NaN undefined), ``cost`` (J,),
  ``uncertainty`` (J,), ``alpha`` (J,), ``radii`` (J, Kmax) NaN padded, ``resolution`` (J,)
  and ``undetermined`` (u,) joint indices (:mod:`jaxskel.joints._determination`);
* ``/skeleton`` (every field of the rigid skeleton, read back exactly by
  :func:`jaxskel.load_skeleton`, :mod:`jaxskel.result._skeleton_file`; ``bone_uncertainty`` (B,)
  beside ``bone_lengths``) and ``/motion`` (when fitted, see docs/result-format.md);
* ``/anatomy`` (when the fit named the body): ``segment_part``, ``segment_confidence``,
  ``notes``, attributes ``humanoid``, ``up``, ``front`` (:mod:`jaxskel.result._anatomy_file`);
* ``/angles`` (a human body with a motion): the anatomical joint angles, ``values`` (F, C)
  radians, ``names``, ``joints``, ``lateral`` (:mod:`jaxskel.result._anatomy_file`);
* ``/diagnostics``: solver ``steps``/``result``/``converged`` per stage,
  ``timings`` as attributes, the cleaning report (``cleaning/duplicates`` and
  ``duplicate_of``: labels merged as copies of another), settings.

Everything is written to a temporary file and renamed into place, so an
interrupted write never leaves a file that looks complete.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .._errors import InputError, SchemaError
from ..io import atomic_output, check_output, input_sources, put, refuse_input
from ._anatomy_file import angles_or_none, write_anatomy, write_angles
from ._skeleton_file import write_skeleton

__all__ = [
    "SCHEMA_VERSION", "ResultFile", "jsonable", "load_result", "open_result", "save_result", "write_cleaning",
    "write_motion", "write_root_attrs",
]

SCHEMA_VERSION = 1


def write_motion(g: h5py.Group, motion: Any) -> None:
    """Fill ``g`` (``/motion``) with a :class:`jaxskel.skeleton.Motion`'s arrays."""
    for src, dst in (
        ("root_position", "root_position"),
        ("rotations", "rotations"),
        ("segment_translations", "segment_translations"),
        ("joint_positions", "joint_positions"),
        ("fitted_markers", "fitted_markers"),
        ("marker_rms", "marker_rms"),
        ("segment_observed", "segment_observed"),
        ("steps", "steps"),
        ("result", "result"),
        ("lowpass_hz", "lowpass_hz"),
    ):
        if getattr(motion, src, None) is not None:
            put(g, dst, np.asarray(getattr(motion, src)))


def write_root_attrs(f: h5py.File, trial: Any) -> None:
    """The attributes on ``/`` of every result file, for the recording ``trial``."""
    from .._version import __version__

    f.attrs["schema_version"] = SCHEMA_VERSION
    f.attrs["jaxskel_version"] = __version__
    f.attrs["source"] = str(trial.source)
    f.attrs["rate"] = float(trial.rate)
    f.attrs["units"] = "m"
    f.attrs["up_axis"] = str(trial.up_axis)
    f.attrs["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat()


@contextlib.contextmanager
def open_result(path: Path, hint: str = "") -> Iterator[h5py.File]:
    """``path`` open for reading, after the checks every reader of a result file makes: it
    exists (:class:`InputError`), is HDF5 and has a ``schema_version`` (:class:`InputError`,
    ``hint`` ending the message), no newer than this jaxskel reads (:class:`SchemaError`)."""
    if not path.is_file():
        raise InputError(f"{path}: no such result file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: cannot read as HDF5 ({exc}){hint}") from None
    with f:
        if "schema_version" not in f.attrs:
            raise InputError(f"{path}: not a jaxskel result file (no schema_version attribute){hint}")
        version = int(f.attrs["schema_version"])
        if version > SCHEMA_VERSION:
            raise SchemaError(
                f"{path}: written with result schema {version}, this jaxskel reads up to "
                f"{SCHEMA_VERSION}; upgrade jaxskel (pip install -U jaxskel)"
            )
        yield f


def write_cleaning(c: h5py.Group, rep: Any) -> None:
    """Fill ``c`` (``/diagnostics/cleaning``) with a :class:`jaxskel.clean.CleaningReport`."""
    put(c, "labels", list(rep.labels))
    put(c, "present_before", rep.present_before)
    put(c, "present_after", rep.present_after)
    put(c, "jump_samples", rep.jump_samples)
    put(c, "trimmed_samples", rep.trimmed_samples)
    put(c, "longest_run_s", rep.longest_run_s)
    put(c, "dropped", list(rep.dropped))
    put(c, "dropped_reason", list(rep.dropped.values()))
    put(c, "duplicates", np.asarray(list(rep.duplicates), dtype=str))
    put(c, "duplicate_of", np.asarray(list(rep.duplicates.values()), dtype=str))


def save_result(
    result: Any,
    path: str | os.PathLike[str],
    *,
    overwrite: bool = False,
    extra_groups: dict[str, Callable[[h5py.Group], None]] | None = None,
) -> Path:
    """Write a :class:`jaxskel.SkeletonResult` to HDF5 (atomic; never overwrites without ``overwrite``).

    ``extra_groups`` maps a group name (e.g. ``"normalized"``) to a function that
    fills that group; later stages add their output this way.
    """
    path = check_output(path, "result")  # a folder, not .h5/.hdf5, an unwritable folder
    refuse_input(path, input_sources(result.trial), "the result file")
    seg = result.segmentation
    topo = result.topology
    angles = angles_or_none(result.skeleton, result.motion, result.anatomy)
    with atomic_output(path, overwrite) as tmp:
        with h5py.File(tmp, "w") as f:
            write_root_attrs(f, result.trial)

            g = f.create_group("markers")
            put(g, "labels", list(result.input_labels))
            put(g, "segment", result.marker_segment_input())
            put(g, "physical", result.physical_input())
            put(g, "used_labels", list(result.trial.labels))
            put(g, "used_segment", np.asarray(seg.marker_segment))
            put(g, "positions", np.asarray(result.trial.positions))

            g = f.create_group("segments")
            put(g, "names", list(result.segment_names))
            put(g, "sizes", seg.segment_sizes)
            put(g, "eigenvalues", seg.eigenvalues)
            put(g, "distance_std", seg.distance_std)
            g.attrs["eigengap_segments"] = seg.eigengap_segments
            g.attrs["count_rule"] = seg.count_rule
            g.attrs["max_segments"] = seg.max_segments
            g.attrs["rigid_limit"] = seg.rigid_limit
            g.attrs["sigma"] = seg.sigma
            g.attrs["white_noise"] = seg.white_noise
            g.attrs["split_from"] = seg.split_from
            g.attrs["rigid_count"] = seg.rigid_count
            put(g, "split_markers", np.asarray(seg.split_markers, dtype=str))
            put(g, "passed_joint_markers", np.asarray(seg.passed_joint_markers, dtype=str).reshape(-1, 3))
            put(g, "left_out_labels", np.asarray(list(seg.left_out), dtype=str))
            put(g, "left_out_reasons", np.asarray(list(seg.left_out.values()), dtype=str))
            put(g, "still_spans", np.asarray(seg.still_spans, dtype=np.int64).reshape(-1, 2))

            g = f.create_group("topology")
            put(g, "joint_cost", topo.pair_costs.cost)
            put(g, "joint_objective", topo.pair_costs.objective)
            g.attrs["joint_cost_weight"] = topo.pair_costs.weight
            put(g, "edges", topo.edges.reshape(-1, 2))
            put(g, "root", np.int64(topo.root))
            put(g, "roots", np.asarray(topo.roots, dtype=int))
            reasons = topo.pair_costs.reasons
            put(g, "infeasible", np.asarray(list(reasons.keys()), dtype=int).reshape(-1, 2))
            put(g, "infeasible_reason", np.asarray(list(reasons.values()), dtype=str))  # str even when empty
            from ..joints import untested_joints

            untested = untested_joints(seg, topo)
            put(g, "untested", np.asarray([u[:3] for u in untested], dtype=int).reshape(-1, 3))
            put(g, "untested_std", np.asarray([u[3:] for u in untested], dtype=float).reshape(-1, 2))
            from ..joints import near_ties

            ties = near_ties(result.trial, seg, topo)
            put(g, "near_ties", np.asarray([[t.joint, *t.rival] for t in ties], dtype=int).reshape(-1, 3))
            put(g, "near_ties_margin", np.asarray([[t.margin, t.noise] for t in ties], dtype=float).reshape(-1, 2))
            if topo.fixed_misfit is not None:
                put(g, "fixed_misfit", topo.fixed_misfit)
            exchanges = topo.pose_exchanges
            pairs = [[*e.removed, *e.added] for e in exchanges]
            put(g, "pose_exchanges", np.asarray(pairs, dtype=int).reshape(-1, 4))
            values = [[*e.misfit, *e.cost] for e in exchanges]
            put(g, "pose_exchanges_values", np.asarray(values, dtype=float).reshape(-1, 4))
            put(g, "pose_exchanges_test", np.asarray([e.test for e in exchanges], dtype=str))
            hung = topo.attachments
            put(g, "attachments", np.asarray([[a.segment, a.host, a.bridge] for a in hung], dtype=int).reshape(-1, 3))
            put(g, "attachments_rigidity", np.asarray([a.rigidity for a in hung], dtype=float))

            g = f.create_group("joints")
            put(g, "positions", topo.joint_positions)
            put(g, "cost", topo.joint_cost)
            put(g, "uncertainty", topo.uncertainty)
            put(g, "alpha", topo.alpha)
            kmax = max((len(r) for r in topo.radii), default=0)
            radii = np.full((len(topo.radii), kmax), np.nan)
            for j, r in enumerate(topo.radii):
                radii[j, : len(r)] = r
            put(g, "radii", radii)
            put(g, "resolution", result.joint_resolutions())
            put(g, "undetermined", np.asarray([u.joint for u in result.undetermined_joints()], dtype=int))

            if result.skeleton is not None:
                write_skeleton(f.create_group("skeleton"), result.skeleton, result.segment_names)
            if result.motion is not None:
                write_motion(f.create_group("motion"), result.motion)
            if result.anatomy is not None:
                write_anatomy(f.create_group("anatomy"), result.anatomy)
            if angles is not None:
                write_angles(f.create_group("angles"), angles)

            d = f.create_group("diagnostics")
            pc = topo.pair_costs
            put(d, "pairs_steps", pc.steps)
            put(d, "pairs_result", pc.result)
            put(d, "pairs_uncertainty", pc.uncertainty)
            put(d, "joints_steps", topo.steps)
            put(d, "joints_result", topo.result)
            put(d, "joints_converged", topo.converged)
            put(d, "segmentation_scores", seg.scores)
            put(d, "trial_bounds", np.asarray(result.trial_bounds, dtype=int).reshape(-1, 2))
            if result.skeleton is not None and getattr(result.skeleton, "diagnostics", None):
                d.attrs["rigid"] = json.dumps(jsonable(result.skeleton.diagnostics))
            for stage, seconds in result.timings.items():
                d.attrs[f"time_{stage.replace(' ', '_')}"] = float(seconds)
            d.attrs["settings"] = json.dumps(jsonable(result.settings))
            if result.cleaning is not None:
                write_cleaning(d.create_group("cleaning"), result.cleaning)
            for name, writer in (extra_groups or {}).items():
                writer(f.create_group(name))
    return path


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values (mappings, lists, numbers, strings; anything else as text)."""
    if isinstance(obj, Mapping):  # dicts and the read-only views results hold
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


class ResultFile:
    """A result file read back: groups as attributes, datasets as numpy arrays.

    >>> r = jaxskel.load_result("out.h5")          # doctest: +SKIP
    >>> r.topology.edges, r.attrs["rate"]           # doctest: +SKIP
    """

    def __init__(self, data: dict[str, Any], attrs: dict[str, Any]):
        self._data = data
        self.attrs = attrs

    def __getattr__(self, name: str) -> Any:
        try:
            return self._data[name]
        except KeyError:
            raise AttributeError(
                f"result has no {name!r}; available: {', '.join(sorted(self._data))}"
            ) from None

    def __getitem__(self, path: str) -> Any:
        node: Any = self
        for part in path.strip("/").split("/"):
            node = getattr(node, part)
        return node

    def __contains__(self, path: str) -> bool:
        try:
            self[path]
            return True
        except AttributeError:
            return False

    def keys(self) -> list[str]:
        return sorted(self._data)

    def __repr__(self) -> str:
        return f"ResultFile({', '.join(self.keys())})"


def _read_group(g: h5py.Group) -> ResultFile:
    data: dict[str, Any] = {}
    for name, item in g.items():
        if isinstance(item, h5py.Group):
            data[name] = _read_group(item)
        else:
            value = item[()]
            if item.dtype.kind == "O" or h5py.check_string_dtype(item.dtype) is not None:
                value = np.asarray(item.asstr()[()], dtype=object)
            data[name] = value
    return ResultFile(data, {k: _attr(v) for k, v in g.attrs.items()})


def _attr(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _with_segment_names(result: ResultFile) -> ResultFile:
    """``result`` with ``/segments/names`` derived from its markers (:mod:`jaxskel.segment._names`)
    where the file has none."""
    if "segments" not in result or "names" in result.segments or "markers/used_segment" not in result:
        return result
    from ..segment import names_from_markers

    n_segments = len(result.segments.sizes) if "sizes" in result.segments else len(result.topology.edges) + 1
    labels = [str(v) for v in result.markers.used_labels]
    result.segments._data["names"] = np.asarray(
        names_from_markers(labels, result.markers.used_segment, n_segments), dtype=object
    )
    return result


def load_result(path: str | os.PathLike[str]) -> ResultFile:
    """Read a result file written by :meth:`SkeletonResult.save`.

    ``/segments/names`` is always there: a file written without segment names gets them
    derived from its markers (:mod:`jaxskel.segment._names`).

    Raises :class:`InputError` for a missing or non-result file and
    :class:`SchemaError` for a file written by a newer, incompatible jaxskel.
    """
    path = Path(path)
    try:
        with open_result(path) as f:
            return _with_segment_names(_read_group(f))
    except OSError as exc:
        raise InputError(f"{path}: cannot read as HDF5 ({exc})") from None
