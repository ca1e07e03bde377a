"""`TrackedTrial`: one trial posed on a saved skeleton (:func:`jaxskel.track`), and its file.

A tracked trial's result file has the fit's layout where the two share a meaning
(docs/result-format.md, "Tracked trials"): ``/@kind = "tracked"`` and ``/@calibration``
(the skeleton's result file), ``/markers`` (``labels`` as in the trial, ``used_labels``
the skeleton's markers, ``positions`` the cleaned trial in that order, ``segment``,
``missing`` and ``extra``), ``/segments/names``, ``/topology`` (``edges``, ``root``),
``/skeleton`` (the calibration's, bit for bit, so :func:`jaxskel.load_skeleton` reads it back
from here too), ``/anatomy`` (the calibration's named body, where it has one), ``/angles`` (its joint angles), ``/motion`` (with ``segment_posed``) and ``/diagnostics``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .._errors import InputError
from ..anatomy import Anatomy, AngleOptions, JointAngles, joint_angles
from ..clean import CleaningReport
from ..io import Trial, atomic_output, check_output, input_sources, put, refuse_input

__all__ = ["TrackedTrial"]


@dataclasses.dataclass(frozen=True, eq=False)
class TrackedTrial:
    """A trial posed on a calibrated skeleton by :func:`jaxskel.track`.

    Attributes
    ----------
    name
        The trial's name (its file's stem).
    trial
        The cleaned trial in the skeleton's marker order (``labels`` are the skeleton's;
        NaN where the trial lacks a marker or a sample).
    input_labels
        The trial's own labels, as loaded.
    skeleton
        The calibration's skeleton, unchanged.
    motion
        Its pose in every frame (:class:`jaxskel.skeleton.Motion`); ``marker_rms`` is the
        per-frame residual against the markers as measured, ``fitted_markers`` the
        gap-filled markers (NaN on a segment in the frames it is not posed).
    segment_posed
        (F, S) True where the segment's pose is known: its markers seen in that frame fix it
        (three of them, all it has, or with its joints three points), or it lies in a gap
        between such frames (filled by the IK). False where the trial cannot say where the
        segment is: too few of its markers in the trial, or before its first / after its
        last posed frame.
    missing_markers, extra_markers
        The skeleton's markers the trial lacks (tracked without them) and the trial's
        markers the skeleton does not know (ignored).
    matched
        Skeleton label -> trial label, for markers matched other than by equal labels
        (a subject prefix such as ``Subject:``, letter case).
    cleaning
        :class:`jaxskel.clean.CleaningReport` of the trial (``None`` without cleaning).
    calibration
        Where the skeleton came from (its result file), ``""`` for one given in memory.
    anatomy
        The calibration's named body (:class:`jaxskel.anatomy.Anatomy`), ``None`` where it
        named none (or the skeleton was given without its result).
    angle_frames
        (S, 3, 3) the calibration's anatomical frames (``/angles/frames`` of its result), in
        which :meth:`joint_angles` measures this take; ``None`` where it has none.
    timings, settings
        Seconds per stage; the settings used.
    """

    name: str
    trial: Trial
    input_labels: tuple[str, ...]
    skeleton: Any
    motion: Any
    segment_posed: np.ndarray
    missing_markers: tuple[str, ...]
    extra_markers: tuple[str, ...]
    matched: dict[str, str]
    cleaning: CleaningReport | None
    calibration: str
    timings: dict[str, float]
    settings: dict[str, Any]
    anatomy: Anatomy | None = None
    angle_frames: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return self.trial.n_frames

    @property
    def segment_names(self) -> tuple[str, ...]:
        return self.skeleton.names()

    def unposed_segments(self) -> dict[str, int]:
        """Segment name -> number of frames it is not posed in (segments posed throughout left out)."""
        counts = (~np.asarray(self.segment_posed)).sum(axis=0)
        return {name: int(n) for name, n in zip(self.segment_names, counts) if n}

    def fitted_trial(self) -> Trial:
        """The fitted, gap-filled markers as a :class:`jaxskel.Trial` (for TRC or C3D)."""
        return self.trial.replace(positions=self.motion.fitted_markers, source=f"jaxskel track ({self.name})")

    def summary(self) -> str:
        """Frames, residual, the markers matched, missing and ignored, the segments not posed."""
        rms = np.asarray(self.motion.marker_rms)
        seen = np.isfinite(rms)
        median = 1e3 * float(np.median(rms[seen])) if seen.any() else float("nan")
        p95 = 1e3 * float(np.percentile(rms[seen], 95)) if seen.any() else float("nan")
        ik = "converged" if self.motion.converged else "hit its step limit in some frames"
        lines = [
            (f"{self.name}: {self.n_frames} frames at {self.trial.rate:g} Hz on the calibration skeleton "
             f"({self.skeleton.n_segments} segments, {len(self.skeleton.marker_labels)} markers)"),
            f"  residual: median {median:.2f} mm, 95th percentile {p95:.2f} mm; IK {ik}",
        ]
        if self.missing_markers:
            lines.append(f"  tracked without {len(self.missing_markers)} markers the trial lacks: "
                         + ", ".join(self.missing_markers))
        if self.extra_markers:
            lines.append(f"  ignored {len(self.extra_markers)} markers the skeleton does not know: "
                         + ", ".join(self.extra_markers))
        if self.matched:
            lines.append("  matched: " + ", ".join(f"{k} <- {v}" for k, v in self.matched.items()))
        unposed = self.unposed_segments()
        if unposed:
            lines.append("  not posed: " + ", ".join(
                f"{name} ({'all' if n == self.n_frames else n} frames)" for name, n in unposed.items()))
        return "\n".join(lines)

    __str__ = summary

    def save(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
        """Write the tracked trial's result file (module docstring), atomically."""
        return save_tracked(self, path, overwrite=overwrite)

    def joint_angles(self, options: AngleOptions | None = None) -> JointAngles:
        """The take's anatomical joint angles (:func:`jaxskel.anatomy.joint_angles`) on the
        calibration's named body, in the calibration's anatomical frames (:attr:`angle_frames`;
        where it has none, frames built from this take); :class:`InputError` where the
        calibration named no body."""
        if self.anatomy is None:
            raise InputError("joint angles need the named body; the calibration's result has no /anatomy "
                             "(refit it with anatomy=True, the default)")
        return joint_angles(self.skeleton, self.motion, self.anatomy, options=options, frames=self.angle_frames)

    def export_bvh(self, path: str | os.PathLike[str], *, overwrite: bool = False, units: str = "cm",
                   rotation_order: str = "ZXY", names: str | Mapping[str, str] | None = None) -> Path:
        """The motion as BVH on the calibration's rig (:func:`jaxskel.result.export_bvh`): every
        trial tracked on one skeleton has the same hierarchy and offsets, the calibration's
        named body (:attr:`anatomy`) setting its axes, T-pose and names; without one the
        recording's up axis is turned to the BVH's Y."""
        from ._bvh import export_bvh

        return export_bvh(self.skeleton, self.motion, path, rate=self.trial.rate, overwrite=overwrite, units=units,
                          labels=self.segment_names, rotation_order=rotation_order, anatomy=self.anatomy, names=names,
                          up_axis=self.trial.up_axis)


def save_tracked(tracked: TrackedTrial, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
    """Write ``tracked`` to ``path`` (``.h5``; never over an input or, without ``overwrite``, a file)."""
    from ._format import jsonable, write_cleaning, write_motion, write_root_attrs
    from ._anatomy_file import angles_or_none, write_anatomy, write_angles
    from ._skeleton_file import write_skeleton

    path = check_output(path, "result")
    refuse_input(path, input_sources(tracked.trial) + ([tracked.calibration] if tracked.calibration else []),
                 "the tracked trial's result file")
    skeleton, trial = tracked.skeleton, tracked.trial
    used = {lab: i for i, lab in enumerate(skeleton.marker_labels)}
    source_of = {v: k for k, v in tracked.matched.items()}
    segment = np.asarray([
        skeleton.marker_segment[used[source_of.get(lab, lab)]] if source_of.get(lab, lab) in used else -1
        for lab in tracked.input_labels
    ], dtype=np.int64)
    angles = angles_or_none(skeleton, tracked.motion, tracked.anatomy, tracked.angle_frames)
    with atomic_output(path, overwrite) as tmp, h5py.File(tmp, "w") as f:
        write_root_attrs(f, trial)
        f.attrs["kind"] = "tracked"
        f.attrs["calibration"] = str(tracked.calibration)
        g = f.create_group("markers")
        put(g, "labels", list(tracked.input_labels))
        put(g, "segment", segment)
        put(g, "used_labels", list(skeleton.marker_labels))
        put(g, "used_segment", np.asarray(skeleton.marker_segment))
        put(g, "positions", np.asarray(trial.positions))
        put(g, "missing", np.asarray(list(tracked.missing_markers), dtype=str))
        put(g, "extra", np.asarray(list(tracked.extra_markers), dtype=str))
        put(g, "matched_labels", np.asarray(list(tracked.matched), dtype=str))
        put(g, "matched_from", np.asarray(list(tracked.matched.values()), dtype=str))
        g = f.create_group("segments")
        put(g, "names", list(tracked.segment_names))
        g = f.create_group("topology")
        put(g, "edges", np.asarray(skeleton.edges).reshape(-1, 2))
        put(g, "root", np.int64(skeleton.root))
        write_skeleton(f.create_group("skeleton"), skeleton)
        if tracked.anatomy is not None:
            write_anatomy(f.create_group("anatomy"), tracked.anatomy)
        if angles is not None:
            write_angles(f.create_group("angles"), angles)
        m = f.create_group("motion")
        write_motion(m, tracked.motion)
        put(m, "segment_posed", np.asarray(tracked.segment_posed))
        d = f.create_group("diagnostics")
        d.attrs["rigid"] = json.dumps(jsonable(skeleton.diagnostics))
        d.attrs["settings"] = json.dumps(jsonable(tracked.settings))
        for stage, seconds in tracked.timings.items():
            d.attrs[f"time_{stage.replace(' ', '_')}"] = float(seconds)
        if tracked.cleaning is not None:
            write_cleaning(d.create_group("cleaning"), tracked.cleaning)
    return path

