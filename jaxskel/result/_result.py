"""`SkeletonResult`: everything one fit produced, with its summary and its exports."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from collections.abc import Mapping
from typing import Any

import numpy as np

from .._errors import InputError
from .._math.frames import cut_frames
from ..anatomy import Anatomy, AngleOptions, JointAngles, joint_angles
from ..clean import CleaningReport
from ..io import Trial
from ..joints import Topology
from ..segment import Segmentation

__all__ = ["SkeletonResult"]


@dataclasses.dataclass(frozen=True)
class SkeletonResult:
    """Everything :func:`fit_skeleton` produced, stage by stage.

    Attributes
    ----------
    input_labels
        Marker labels of the input (after combining trials), as given.
    trial
        The cleaned (and label-merged) trial every later stage used.
    cleaning
        :class:`CleaningReport` (``None`` when cleaning was switched off).
    label_mapping
        Result of passive-marker merging, or ``None``.
    segmentation, topology
        Stage outputs (:class:`Segmentation`, :class:`Topology`).
    skeleton, motion
        Rigid skeleton and inverse-kinematics motion (``None`` when switched off).
    segment_names
        (S,) unique readable names, from the segments' marker labels unless given
        (:mod:`jaxskel.segment._names`: ``RTH`` for ``RTHPA, RTHPP, RTHDP, RTHDA``,
        ``LFWT+RFWT+LBWT+RBWT`` where the labels share no prefix). Display only: no stage
        of the fit reads them. Joints are named ``parent-child`` from them.
    trial_bounds
        Frame range of each input trial in the combined recording.
    timings
        Seconds per stage.
    settings
        The arguments used.
    anatomy
        The body part of every segment (:class:`jaxskel.anatomy.Anatomy`), or ``None`` when
        the fit did not name the body (``anatomy=False``, no rigid skeleton). Where it names
        a segment's part, :attr:`segment_names` holds the part (``thigh_l``) and
        :meth:`joint_name` the joint (``knee_l``).
    """

    input_labels: tuple[str, ...]
    trial: Trial
    cleaning: CleaningReport | None
    label_mapping: Any
    segmentation: Segmentation
    topology: Topology
    skeleton: Any
    motion: Any
    segment_names: tuple[str, ...]
    trial_bounds: tuple[tuple[int, int], ...]
    timings: dict[str, float]
    settings: dict[str, Any]
    anatomy: Anatomy | None = None

    # ------------------------------------------------------------- derived
    @property
    def n_segments(self) -> int:
        return self.segmentation.n_segments

    @property
    def edges(self) -> np.ndarray:
        return self.topology.edges

    @property
    def joint_positions(self) -> np.ndarray:
        """(F, J, 3) joint centres per frame (row j <-> edge j)."""
        return self.topology.joint_positions

    def marker_segment_input(self) -> np.ndarray:
        """Segment of every *input* marker (-1 if dropped by cleaning; a merged or duplicate
        label has its physical marker's segment)."""
        index = {lab: i for i, lab in enumerate(self.segmentation.labels)}
        phys = self.physical_input()
        out = np.full(len(self.input_labels), -1, dtype=int)
        merged_labels = self.trial.labels
        for i, lab in enumerate(self.input_labels):
            target = merged_labels[phys[i]] if phys[i] >= 0 else None
            if target is not None and target in index:
                out[i] = self.segmentation.marker_segment[index[target]]
        return out

    def physical_input(self) -> np.ndarray:
        """Physical-marker index (into ``trial.labels``) of every input label, -1 if none.

        A duplicate label merged by cleaning maps to the marker it was merged into."""
        index = {lab: i for i, lab in enumerate(self.trial.labels)}
        copy_of = self.cleaning.duplicates if self.cleaning is not None else {}

        def find(lab: str) -> int:
            while lab not in index and lab in copy_of:
                lab = copy_of[lab]
            return index.get(lab, -1)

        if self.label_mapping is not None:
            # The mapping covers the labels that reached the merge; cleaning may have
            # dropped others first (never seen, or a copy of another label).
            merged = tuple(self.label_mapping.physical_labels)
            via = {lab: (merged[p] if p >= 0 else None)
                   for lab, p in zip(self.label_mapping.labels, np.asarray(self.label_mapping.physical).tolist())}

            def find_merged(lab: str) -> int:
                while lab not in via and lab in copy_of:
                    lab = copy_of[lab]
                target = via.get(lab)
                return find(target) if target is not None else -1

            return np.array([find_merged(lab) for lab in self.input_labels], dtype=int)
        return np.array([find(lab) for lab in self.input_labels], dtype=int)

    def bone_lengths(self) -> dict[str, float]:
        """Distance between the two joints of every segment with two or more joints.

        Taken from the rigid skeleton when it exists, else the median over frames
        of the per-frame joint distances.
        """
        out: dict[str, float] = {}
        if self.skeleton is not None:
            for (j0, j1), length in zip(self.skeleton.bones, self.skeleton.bone_lengths):
                out[self.bone_name(j0, j1)] = float(length)
            return out
        jp = self.joint_positions
        edges = self.edges
        for s in range(self.n_segments):
            js = [j for j, (p, c) in enumerate(edges) if p == s or c == s]
            for a in range(len(js)):
                for b in range(a + 1, len(js)):
                    d = np.linalg.norm(jp[:, js[a]] - jp[:, js[b]], axis=-1)
                    if np.isfinite(d).any():
                        out[self.bone_name(js[a], js[b])] = float(np.nanmedian(d))
        return out

    def bone_name(self, j0: int, j1: int) -> str:
        """``"B (A-C)"``: segment B between its joints with segments A and C."""
        names = self.segment_names
        e0, e1 = {int(v) for v in self.edges[j0]}, {int(v) for v in self.edges[j1]}
        shared = (e0 & e1).pop()
        return f"{names[shared]} ({names[(e0 - {shared}).pop()]}-{names[(e1 - {shared}).pop()]})"

    def untested_joints(self) -> list:
        """Sparsely marked segments whose likelier joint could not be tested
        (:func:`jaxskel.joints.untested_joints`)."""
        from ..joints import untested_joints

        return untested_joints(self.segmentation, self.topology)

    def undetermined_joints(self) -> list:
        """Tree joints whose centre the recording fixes only to within more than 10 cm
        (:func:`jaxskel.joints.undetermined_joints`); empty without the rigid skeleton."""
        from ..joints import undetermined_joints

        return undetermined_joints(self.skeleton) if self.skeleton is not None else []

    def joint_resolutions(self) -> np.ndarray:
        """(J,) metres: how far each joint centre can move along its least determined
        direction before the fit's misfit doubles (:mod:`jaxskel.joints._determination`); NaN
        where unknown (no segment of the joint with three markers, no rigid skeleton)."""
        from ..joints import joint_resolution

        if self.skeleton is None:
            return np.full(len(self.edges), np.nan)
        return joint_resolution(self.skeleton)

    def bone_uncertainties(self) -> dict[str, float]:
        """How far each bone length of :meth:`bone_lengths` can move with its joints inside
        their resolutions (metres, NaN where unknown; :func:`jaxskel.joints.bone_uncertainty`).
        Empty without the rigid skeleton."""
        if self.skeleton is None:
            return {}
        from ..joints import bone_uncertainty

        spread = bone_uncertainty(self.skeleton)
        return {self.bone_name(j0, j1): float(u) for (j0, j1), u in zip(self.skeleton.bones, spread)}

    def near_ties(self, z: float = 2.0) -> list:
        """Tree joints whose cost is within the sampling noise of a rival pair's, the pair
        the tree would joint instead (:func:`jaxskel.joints.near_ties`)."""
        from ..joints import near_ties

        return near_ties(self.trial, self.segmentation, self.topology, z=z)

    def joint_name(self, j: int) -> str:
        """Joint ``j``'s anatomical name (``knee_l``) where :attr:`anatomy` gives its two
        segments' parts, else ``parent-child`` from :attr:`segment_names`."""
        p, c = (int(v) for v in self.edges[j])
        fallback = f"{self.segment_names[p]}-{self.segment_names[c]}"
        return self.anatomy.joint_names([[p, c]], (fallback,))[0] if self.anatomy is not None else fallback

    def summary(self) -> str:
        """Segments with their markers, joints with their costs, how the tree was chosen and
        its runner-up, bone lengths. A joint the recording fixes only to within more than
        10 cm reads ``undetermined``, with the motion that would fix it, and so does the
        bound of a bone ending at it (:func:`jaxskel.result._report.summary_text`)."""
        from ._report import summary_text

        return summary_text(self)

    __str__ = summary

    def save(self, path: str, *, overwrite: bool = False, extra_groups: dict[str, Any] | None = None) -> None:
        """Write the HDF5 result file (schema in the README), atomically.

        ``extra_groups`` maps group names to functions filling them (used for
        ``/normalized`` and ``/parameters``).
        """
        from ..result._format import save_result

        save_result(self, path, overwrite=overwrite, extra_groups=extra_groups)

    def joint_angles(self, options: AngleOptions | None = None) -> JointAngles:
        """The anatomical joint angles of the motion (:func:`jaxskel.anatomy.joint_angles`:
        Grood–Suntay frames, ISB signs, radians), every frame of the fitted recording.

        ``options`` is a :class:`jaxskel.anatomy.AngleOptions` (which joints are hinges).
        Raises :class:`InputError` without a motion or a human :attr:`anatomy`."""
        if self.skeleton is None or self.motion is None:
            raise InputError("joint angles need the rigid skeleton and its motion; fit with rigid=True and ik=True "
                             "(the defaults)")
        if self.anatomy is None:
            raise InputError("joint angles need the named body; fit with anatomy=True (the default; not --no-anatomy)")
        return joint_angles(self.skeleton, self.motion, self.anatomy, options=options)

    def export_bvh(
        self,
        path: str,
        *,
        trial: int | None = None,
        overwrite: bool = False,
        units: str = "cm",
        rotation_order: str = "ZXY",
        names: str | Mapping[str, str] | None = None,
    ) -> Path:
        """Write the rigid skeleton and its IK motion as BVH (:func:`jaxskel.result.export_bvh`),
        at the recording's frame rate, Y up: for a human :attr:`anatomy`, facing +Z in a
        T-pose rest with ``names`` (default Mixamo's); otherwise segments named by
        :attr:`segment_names`, the recording's up axis turned to Y.

        ``trial`` picks one input trial of a joint fit (its frames, ``trial_bounds``);
        ``None`` writes every frame of the fitted recording, the trials one after another.
        Returns the path written.
        """
        if self.skeleton is None or self.motion is None:
            raise InputError(
                "export_bvh needs the rigid skeleton and its motion; fit with rigid=True and ik=True (the defaults)"
            )
        motion = self.motion
        if trial is not None:
            n = len(self.trial_bounds)
            if isinstance(trial, bool) or not isinstance(trial, (int, np.integer)) or not 0 <= trial < n:
                raise InputError(f"trial must be an index 0..{n - 1} of the {n} fitted trial(s), got {trial!r}")
            start, stop = self.trial_bounds[int(trial)]
            motion = cut_frames(motion, motion.n_frames, slice(start, stop))
        from ..result._bvh import export_bvh

        return export_bvh(
            self.skeleton, motion, path, rate=self.trial.rate, overwrite=overwrite, units=units,
            labels=self.segment_names, rotation_order=rotation_order, anatomy=self.anatomy, names=names,
            up_axis=self.trial.up_axis,
        )

    def export_osim(self, path: str, *, overwrite: bool = False, frame: int | None = None) -> Path:
        """Write the rigid skeleton as an OpenSim 4 model (:func:`jaxskel.result.export_osim`):
        bodies named by :attr:`segment_names`, markers by their labels, the recording's up axis
        turned to OpenSim's Y, and the default pose the motion's ``frame`` (default: the rest
        frame of the rigid fit). Returns the path written."""
        if self.skeleton is None:
            raise InputError("export_osim needs the rigid skeleton; fit with rigid=True (the default)")
        from ..result._osim import export_osim

        motion = self.motion
        if motion is not None and frame is None:
            frame = int(self.skeleton.diagnostics.get("rest_frame", 0))
        return export_osim(self.skeleton, path, motion=motion, frame=0 if frame is None else frame, up_axis=self.trial.up_axis,
                           segment_names=self.segment_names, overwrite=overwrite, anatomy=self.anatomy)
