"""The stage plan: the order of a fit's stages, one plan for the single fit and the batch.

    Trial(s) --prepare--> PreparedFit            clean, [merge labels], segment
             --joints---> Topology               all-pairs joint costs, MST, tree joints
             --skeleton-> SkeletonResult         rigid skeleton (no motion yet)
             --complete-> SkeletonResult         grow the automatic count where a segment is
                                                 not rigid, inverse kinematics, confirm merges

:func:`jaxskel.fit_skeleton` runs :meth:`StagePlan.fit`. :func:`jaxskel.fit_batch` runs
:meth:`StagePlan.prepare` for each trial, solves the joint stage of many trials in shared
vmapped solves, and hands each trial's tree to :meth:`StagePlan.complete`, so both fit
with the same stages, in the same order, from the same :class:`FitOptions`. Each stage is
a public function of its own package too (:func:`jaxskel.clean.clean`,
:func:`jaxskel.relabel.merge_labels`, :func:`jaxskel.segment.segment_markers`,
:func:`jaxskel.joints.fit_topology`, :func:`jaxskel.skeleton.fit_rigid`,
:func:`jaxskel.skeleton.inverse_kinematics`); the plan only sequences them, keeps every
stage's output and diagnostics, and reports progress.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any, ClassVar

import numpy as np

from .._errors import DegenerateMotionError, DegenerateMotionWarning, InputError, NonRigidMarkerWarning
from ..anatomy import identify_result
from ..clean import CleaningReport, Lowpassed, check_cutoff, clean, lowpass_markers
from ..io import Trial, median_extent, units_problem
from ..joints import Topology, anchored_centres, fit_topology, joint_costs, near_ties, untested_joints
from ..relabel import LabelMapping, confirm_merges, merge_labels, needs_merging
from ..result import SkeletonResult, nonrigid_text
from ..segment import Segmentation, combine_trials, left_out_markers, segment_markers, still_trials, white_noise
from ..segment import segment_names as default_names
from ..skeleton import SOLVED_JOINT_WEIGHT, Motion, Skeleton, fit_rigid, inverse_kinematics, measured_rms, solver_shape
from ._options import FitOptions
from ._split_refit import MAX_SPLITS, crowded_nonrigid, keep_split, read_scatter, replay, scatter_splits
from ._warnings import (
    STACKLEVEL,
    require_one_tree,
    warn_near_ties,
    warn_nonrigid_groups,
    warn_undetermined,
    warn_unexercised,
    warn_untested,
)

__all__ = ["PreparedFit", "StagePlan", "as_trials", "check_marker_sets", "check_units", "moving_frames"]


def check_units(trial: Trial) -> None:
    """Raise :class:`InputError` when positions are clearly not in metres.

    The median over frames of the body's span must lie in
    :data:`jaxskel.io.PLAUSIBLE_SPAN` (2 cm to 40 m); the message says what to do
    for where the positions came from (:func:`jaxskel.io.units_problem`).
    """
    if median_extent(np.asarray(trial.positions)) is None:
        raise InputError(f"{trial.source or 'trial'}: no frame has two markers present; there is nothing to fit")
    problem = units_problem(trial)
    if problem is not None:
        raise InputError(problem)


# Vicon's names for trajectories that were never labelled: they differ between recordings.
_UNLABELED = re.compile(r"^\*\d+$")


def check_marker_sets(trials: Sequence[Trial]) -> None:
    """Raise :class:`InputError` when trials fitted together do not share their markers.

    Markers are matched across trials by label. A trial may lack markers another has (a
    motion trial without the calibration trial's extra markers, a marker lost), as long
    as one trial holds every labelled marker of the others; otherwise the labels name
    different markers, or the same markers differently, and the fit would end in a
    forest of segments never seen together. Unlabelled ``*N`` trajectories are left out.
    """
    if len(trials) < 2:
        return
    named = [{lab for lab in t.labels if not _UNLABELED.match(lab)} for t in trials]
    union = set().union(*named)
    if any(markers == union for markers in named):
        return
    order = list(dict.fromkeys(lab for t in trials for lab in t.labels if lab in union))
    names = [str(t.metadata.get("file") or t.source or f"trial {i + 1}") for i, t in enumerate(trials)]
    parts = []
    for i, markers in enumerate(named):
        lacks = [lab for lab in order if lab not in markers]
        if lacks:
            holders = [names[j] for j, other in enumerate(named) if j != i and other & set(lacks)]
            shown = ", ".join(lacks[:8]) + (f" and {len(lacks) - 8} more" if len(lacks) > 8 else "")
            parts.append(f"{names[i]} lacks {shown} (in {', '.join(holders)})")
    raise InputError(
        "the trials fitted together have different markers (they are matched by label, and no trial has all "
        f"of them): {'; '.join(parts)}. Fit them separately, rename the markers to match, or keep the markers "
        "they share (Trial.select_markers)"
    )


def moving_frames(trial: Trial, segmentation: Segmentation) -> Trial:
    """``trial`` with the frames of its still trials (``segmentation.still_spans``) blanked:
    what the joint stages read."""
    if not segmentation.still_spans:
        return trial
    positions = np.array(trial.positions, copy=True)
    for start, stop in segmentation.still_spans:
        positions[start:stop] = np.nan
    return trial.replace(positions=positions)


def as_trials(trial_or_trials: Trial | Sequence[Trial]) -> list[Trial]:
    """One trial or a non-empty sequence of trials, as a list (else :class:`InputError`)."""
    if isinstance(trial_or_trials, Trial):
        return [trial_or_trials]
    if isinstance(trial_or_trials, (str, bytes)) or not isinstance(trial_or_trials, Sequence):
        raise InputError(
            "fit_skeleton takes a jaxskel.Trial or a list of Trials; load files with jaxskel.load(path)"
        )
    trials = list(trial_or_trials)
    if not trials or not all(isinstance(t, Trial) for t in trials):
        raise InputError("fit_skeleton takes a non-empty list of jaxskel.Trial objects")
    return trials


@dataclasses.dataclass
class PreparedFit:
    """A fit after the host-side stages (clean, merge labels, segment).

    The state a fit carries between its stages; :func:`jaxskel.fit_batch` solves the
    joint stage of several prepared fits together.
    """

    input_labels: tuple[str, ...]
    trial: Trial
    cleaning: CleaningReport | None
    label_mapping: LabelMapping | None
    segmentation: Segmentation
    trial_bounds: tuple[tuple[int, int], ...]
    timings: dict[str, float]
    #: The cleaned trial given to merge_labels (``None`` without merging): the
    #: skeleton's confirmation of the merges starts again from it.
    merge_input: Trial | None = None
    #: The markers left out of the grouping (:attr:`Segmentation.left_out`), on the fit's
    #: frames: landmarks that may still place a hinge they straddle (``None``: none).
    landmarks: Trial | None = None


@dataclasses.dataclass(frozen=True)
class StagePlan:
    """The stages of a fit with given :class:`FitOptions`, in order.

    ``segment_names`` names the segments (display only; default: from their markers'
    labels). ``on_stage(name)`` is called as each stage ends (a progress bar);
    ``on_more(names)`` when the plan will run stages beyond :attr:`stages`, before they run:
    a grown segment count (``split``, then :attr:`refit_stages`), the label merges checked
    against the skeleton (``confirm merges``) and the fit again after a corrected merge.
    ``device_lock`` is held around the preparation's stages that run JAX code (label
    merging, segmentation), so that other threads may run the numpy-only ones
    (:func:`jaxskel.fit_batch`).
    """

    options: FitOptions = dataclasses.field(default_factory=FitOptions)
    segment_names: tuple[str, ...] | None = None
    on_stage: Callable[[str], None] | None = None
    on_more: Callable[[tuple[str, ...]], None] | None = None
    device_lock: contextlib.AbstractContextManager[Any] | None = None

    #: The stages :meth:`refit` reports, in order (what a grown count runs again).
    refit_stages: ClassVar[tuple[str, ...]] = ("joint costs", "tree joints", "rigid")

    @property
    def stages(self) -> tuple[str, ...]:
        """The names of the stages this plan runs, in order (what ``on_stage`` reports)."""
        o = self.options
        names = ["clean", "merge labels", "segment", "joint costs", "tree joints"]
        if o.skeleton.enabled:
            names += ["rigid", "ik"] if o.motion.enabled else ["rigid"]
            names += ["anatomy"] if o.body.enabled else []
        return tuple(names)

    def _more(self, *names: str) -> None:
        """Announce stages beyond :attr:`stages` that are about to run (``on_more``)."""
        if self.on_more is not None:
            self.on_more(names)

    @contextlib.contextmanager
    def stage(self, prep: PreparedFit, name: str) -> Iterator[None]:
        """Time a stage into ``prep.timings`` (seconds) and report it to ``on_stage``."""
        t0 = time.perf_counter()
        yield
        prep.timings[name] = prep.timings.get(name, 0.0) + time.perf_counter() - t0
        if self.on_stage is not None:
            self.on_stage(name)

    # ------------------------------------------------------------- the stages
    def prepare(self, trial_or_trials: Trial | Sequence[Trial]) -> PreparedFit:
        """Check units, clean, merge labels, segment."""
        o = self.options
        device = self.device_lock if self.device_lock is not None else contextlib.nullcontext()
        trials = as_trials(trial_or_trials)
        for t in trials:
            check_units(t)
        check_marker_sets(trials)
        combined = combine_trials(trials)
        bounds = tuple(combined.metadata.get("trial_bounds", ((0, combined.n_frames),)))
        check_cutoff(o.motion.lowpass, rate=combined.rate, allow_none=True)  # below the Nyquist frequency
        prep = PreparedFit(
            input_labels=combined.labels, trial=combined, cleaning=None, label_mapping=None,
            segmentation=None, trial_bounds=bounds, timings={},  # type: ignore[arg-type]
        )
        work = combined
        # Decide on label merging from the raw data: cleaning's short-run rule would
        # otherwise drop the short relabelled fragments before they can be merged.
        do_merge = self._merges(work)
        report = None
        with self.stage(prep, "clean"):
            if o.clean.enabled:
                kwargs = o.clean.kwargs()
                if do_merge:
                    kwargs["min_run_s"] = 0.0
                work, report = clean(work, **kwargs)
        mapping = None
        with self.stage(prep, "merge labels"), device:
            if do_merge:
                prep.merge_input = work
                work, mapping = merge_labels(work)
                work, report = self._clean_merged(work, report)
        if work.n_markers < 3:
            raise DegenerateMotionError(_too_few_markers(work, combined, report))
        with self.stage(prep, "segment"), device:
            work, left_out, prep.landmarks = self._leave_out(work)
            segmentation = dataclasses.replace(self._segment(work), left_out=left_out,
                                               still_spans=self._still_spans(work, bounds))
        prep.trial, prep.cleaning, prep.label_mapping, prep.segmentation = work, report, mapping, segmentation
        return prep

    def joints(self, prep: PreparedFit) -> Topology:
        """All-pairs joint costs, then the tree and its joints on all frames (but the still
        trials', which say nothing about joints: :attr:`Segmentation.still_spans`)."""
        j = self.options.joints
        moving = moving_frames(prep.trial, prep.segmentation)
        with self.stage(prep, "joint costs"):
            pairs = joint_costs(moving, prep.segmentation, alpha=j.alpha, max_frames=j.topology_frames,
                                method=j.method)
        with self.stage(prep, "tree joints"):
            return fit_topology(
                moving, prep.segmentation, pairs, root=j.root, alpha=j.alpha, alpha_tree=j.alpha_tree,
                method=j.method, pose_check=j.pose_check,
            )

    def skeleton(self, prep: PreparedFit, topology: Topology) -> SkeletonResult:
        """The rigid skeleton on a tree (no motion: :meth:`motion` adds it)."""
        o = self.options
        segmentation, work = prep.segmentation, prep.trial
        names = self.segment_names if self.segment_names is not None else default_names(segmentation.groups)
        if len(names) != segmentation.n_segments:
            raise InputError(f"segment_names has {len(names)} names for {segmentation.n_segments} segments")
        warn_nonrigid_groups(segmentation, names)
        warn_untested(untested_joints(segmentation, topology), names, segmentation.segment_sizes)
        warn_near_ties(near_ties(work, segmentation, topology), names)
        skeleton = None
        rigid = o.skeleton.enabled and len(topology.edges) > 0
        if rigid:
            require_one_tree(topology, segmentation, names)
        with self.stage(prep, "rigid") if o.skeleton.enabled else contextlib.nullcontext():  # as `stages` lists
            if rigid:
                try:
                    skeleton = self._rigid(work, segmentation, topology, names, prep.landmarks)
                except DegenerateMotionError as error:
                    # the segments and joints stand without it: keep them, and say why there is no skeleton
                    warnings.warn(
                        f"the rigid skeleton could not be fitted, so the result has no skeleton and no motion "
                        f"(its segments, tree and joint centres stand): {error}",
                        DegenerateMotionWarning,
                        stacklevel=STACKLEVEL - 1,
                    )
        return SkeletonResult(
            input_labels=prep.input_labels, trial=work, cleaning=prep.cleaning, label_mapping=prep.label_mapping,
            segmentation=segmentation, topology=topology, skeleton=skeleton, motion=None, segment_names=names,
            trial_bounds=prep.trial_bounds, timings=dict(prep.timings), settings=o.record(),
        )

    def motion(self, prep: PreparedFit, result: SkeletonResult) -> SkeletonResult:
        """``result`` with its motion: inverse kinematics, as the options ask."""
        o = self.options
        if not (o.motion.enabled and o.skeleton.enabled):  # not a stage of this plan (`stages`)
            return dataclasses.replace(result, timings=dict(prep.timings))
        with self.stage(prep, "ik"):
            motion = self._inverse_kinematics(result.skeleton, result.trial)
        return dataclasses.replace(result, motion=motion, timings=dict(prep.timings))

    def refit(self, prep: PreparedFit) -> SkeletonResult:
        """The joint and skeleton stages of a prepared fit (no motion)."""
        return self.skeleton(prep, self.joints(prep))

    def complete(self, prep: PreparedFit, topology: Topology | None = None, *, stacklevel: int = 2) -> SkeletonResult:
        """Everything after the preparation, from ``topology`` if the joint stage was solved
        already (:func:`jaxskel.fit_batch`): the skeleton, the automatic count grown where a
        segment is not rigid, the motion, and the label merges confirmed. The fit's warnings
        point ``stacklevel`` frames above this call (as :func:`warnings.warn`'s)."""
        result = self.grow_count(prep, topology, stacklevel=stacklevel + 1)
        if self.options.labels.confirm and prep.label_mapping is not None and result.motion is not None:
            result = self._confirm_merges(prep, result)
        return self.name_body(prep, result)

    def name_body(self, prep: PreparedFit, result: SkeletonResult) -> SkeletonResult:
        """``result`` with its body parts (:func:`jaxskel.anatomy.identify_result`), as the
        options ask: the parts name the segments (where the caller gave no names) and the
        skeleton's segments, so that a tracked take inherits them."""
        if not (self.options.body.enabled and result.skeleton is not None):
            return result
        with self.stage(prep, "anatomy"):
            anatomy = identify_result(result)
        names = result.segment_names if self.segment_names is not None else anatomy.segment_names(result.segment_names, result.edges)
        return dataclasses.replace(
            result, anatomy=anatomy, segment_names=names, timings=dict(prep.timings),
            skeleton=dataclasses.replace(result.skeleton, segment_names=names),
        )

    def fit(self, trial_or_trials: Trial | Sequence[Trial], *, stacklevel: int = 2) -> SkeletonResult:
        """The whole plan: :meth:`prepare`, then :meth:`complete` (warnings ``stacklevel``
        frames above this call)."""
        prep = self.prepare(trial_or_trials)
        return self.complete(prep, stacklevel=stacklevel + 1)

    def grow_count(self, prep: PreparedFit, topology: Topology | None = None, *, stacklevel: int = 2) -> SkeletonResult:
        """Fit a prepared fit, growing its automatic count while a group of three or more
        markers holds two or more that its Procrustes scatter or the rigid skeleton flags
        (:mod:`jaxskel.pipeline._split_refit`), then add the motion.

        The first fit is the plan's skeleton on ``topology`` (its joint stage solved already,
        by :func:`jaxskel.fit_batch`) or on the plan's own joint stage; each grown count is
        segmented and fitted again by this plan. The kept fit's warnings are re-emitted at
        ``stacklevel`` frames above this call (as :func:`warnings.warn`'s).
        """
        options = self.options
        growable = options.segment.n_segments is None and options.skeleton.enabled
        with warnings.catch_warnings(record=True) as caught:
            result = self.skeleton(prep, topology if topology is not None else self.joints(prep))
        kept_warnings = list(caught)
        base = result.segmentation
        n = base.n_segments
        reading = read_scatter(result.trial, result.segmentation) if growable else None  # of the kept fit
        for _ in range(MAX_SPLITS if growable else 0):
            # Each count is tried even when the one before was not kept: one more segment
            # can cut a joined group where it is not the pair the flags name, and the next
            # count then cuts the flagged pair too.
            scattered = reading.crowded
            crowded = crowded_nonrigid(result.skeleton)
            n += 1
            if not (scattered or crowded) or n > min(base.max_segments, result.trial.n_markers):
                break
            self._more("split")
            with self.stage(prep, "split"):
                grown = self._segment(result.trial, n)
            by_scatter = bool(scattered) and scatter_splits(reading, read_scatter(result.trial, grown), grown, base)
            if not by_scatter and not crowded:
                continue  # only the scatter flags, and this count does not mend them: nothing to fit
            self._more(*self.refit_stages)  # a progress bar's total grows by the refit's stages
            flagged = tuple(lab for lab in result.trial.labels if lab in set(scattered) | set(crowded))
            grown = dataclasses.replace(
                grown, count_rule="split", eigengap_segments=base.eigengap_segments, rigid_limit=base.rigid_limit,
                split_from=base.split_from or base.n_segments,
                split_markers=result.segmentation.split_markers + flagged,
                left_out=base.left_out, still_spans=base.still_spans,
            )
            with warnings.catch_warnings(record=True) as caught:
                try:
                    candidate = self.refit(dataclasses.replace(prep, trial=result.trial, segmentation=grown))
                except DegenerateMotionError:  # e.g. a split-off marker no joint can attach: not a candidate
                    continue
            keep = candidate.skeleton is not None if by_scatter else keep_split(result, candidate, base, grown)
            if keep:
                result, kept_warnings = candidate, list(caught)
                reading = read_scatter(result.trial, result.segmentation)
        replay(kept_warnings, stacklevel)
        return self.motion(prep, result)

    # ------------------------------------------------------------- internals
    def _merges(self, work: Trial) -> bool:
        merge = self.options.labels.merge
        if merge != "auto":
            return bool(merge)
        do_merge = needs_merging(work) and any(lab.startswith("*") for lab in work.labels)
        if needs_merging(work) and not do_merge:
            warnings.warn(
                "this recording has more labels than markers in any frame, but its labels are named, "
                "so labels were not merged; pass merge_labels=True (CLI: --merge-labels yes) if it "
                "comes from a passive system that relabels markers after occlusions",
                DegenerateMotionWarning,
                stacklevel=5,
            )
        return do_merge

    def _clean_merged(self, work: Trial, report: CleaningReport | None) -> tuple[Trial, CleaningReport | None]:
        """After merging labels: drop physical markers that are still short-lived (not without cleaning)."""
        if not self.options.clean.enabled:
            return work, report
        work, after = clean(work, trim_s=0.0, reject_jumps=False, min_run_s=self.options.clean.min_run_s)
        return work, dataclasses.replace(
            report, dropped={**report.dropped, **after.dropped}, duplicates={**report.duplicates, **after.duplicates}
        )

    def _still_spans(self, work: Trial, bounds: Sequence[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
        """The frame ranges of the trials in which no two segments move (:func:`still_trials`)."""
        s = self.options.segment
        if not s.leave_out or s.rigid_ratio is None or len(bounds) < 2:
            return ()
        still = still_trials(work, tuple(bounds), white_noise=white_noise(work.positions), sigma=s.sigma,
                             sigma_min=s.sigma_min, sigma_factor=s.sigma_factor, rigid_ratio=s.rigid_ratio)
        return tuple(tuple(bounds[i]) for i in still)

    def _leave_out(self, work: Trial) -> tuple[Trial, dict[str, str], Trial | None]:
        """The trial without the markers the motion cannot place, why each was left out
        (:func:`jaxskel.segment.left_out_markers`; nothing with ``leave_out=False``), and
        those markers as a trial (landmarks for the hinges they straddle; ``None``: none)."""
        s = self.options.segment
        if not s.leave_out or s.rigid_ratio is None:
            return work, {}, None
        left = left_out_markers(work, white_noise=white_noise(work.positions), sigma=s.sigma,
                                sigma_min=s.sigma_min, sigma_factor=s.sigma_factor, rigid_ratio=s.rigid_ratio)
        if not left or len(left.labels) > work.n_markers - 3:
            return work, {}, None
        warnings.warn(
            f"{len(left.labels)} marker(s) left out of the skeleton, the motion cannot place them: "
            + "; ".join(f"{lab}: {why}" for lab, why in left.reasons.items()),
            DegenerateMotionWarning, stacklevel=STACKLEVEL,
        )
        return work.drop_markers(list(left.labels)), dict(left.reasons), work.select_markers(list(left.labels))

    def _segment(self, work: Trial, n_segments: int | None = None) -> Segmentation:
        if work.n_markers < 3:  # after a corrected label merge (prepare says why for the recording itself)
            raise DegenerateMotionError(
                f"only {work.n_markers} markers remain after merging labels; a skeleton needs at least 3 "
                "(see the label mapping and the cleaning report for what was merged or dropped)"
            )
        s = self.options.segment
        n = s.n_segments if n_segments is None else n_segments
        return segment_markers(work, n, seed=self.options.seed, **s.kwargs())

    def _rigid(self, work: Trial, segmentation: Segmentation, topology: Topology, names: Sequence[str],
               landmarks: Trial | None = None) -> Skeleton:
        o = self.options.skeleton
        sliding = np.asarray(topology.undetermined) > 0 if o.hinge_centres == "limb_plane" else None
        centres, anchored = topology.joint_positions, None
        if o.joint_centres == "anchored":
            x, mask = moving_frames(work, segmentation).to_arrays()
            anchored = anchored_centres(x, mask, segmentation.marker_segment, topology.edges, topology.joint_positions)
            centres = anchored.joint_positions
        skeleton = fit_rigid(
            work, segmentation.marker_segment, topology.edges, centres, root=topology.root,
            sliding_joints=sliding, joint_weight=SOLVED_JOINT_WEIGHT, landmarks=landmarks,
        )
        skeleton = dataclasses.replace(skeleton, segment_names=tuple(names))
        if anchored is not None:
            report = {k: v for k, v in vars(anchored).items() if k != "joint_positions"}
            skeleton = dataclasses.replace(skeleton, diagnostics={**skeleton.diagnostics, "anchored": report})
            warn_unexercised(anchored.exercise, [f"{names[p]}-{names[c]}" for p, c in topology.edges])
            warn_undetermined(skeleton, names)
        nonrigid = nonrigid_text(skeleton, names, segmentation.n_segments)
        if nonrigid is not None:
            warnings.warn(f"markers {nonrigid}", NonRigidMarkerWarning, stacklevel=STACKLEVEL - 1)
        return skeleton

    def _inverse_kinematics(self, skeleton: Skeleton | None, work: Trial) -> Motion | None:
        """The IK stage: the skeleton's motion over ``work``, or ``None`` (no skeleton, or IK off)."""
        o = self.options.motion
        if not (o.enabled and skeleton is not None):
            return None
        # the refinement's slot count: its compiled solver serves the IK too
        slots, _ = solver_shape(skeleton.marker_segment, skeleton.edges, skeleton.marker_segment.shape[0])
        if o.lowpass is None:
            return inverse_kinematics(skeleton, work, slots=slots)
        # IK poses every frame on its own: the markers' white noise is filtered out first
        low: Lowpassed = lowpass_markers(work, o.lowpass)
        motion = inverse_kinematics(skeleton, low.trial, slots=slots)
        # the residual is reported against the markers as measured, not as filtered
        column = work.marker_index(motion.marker_labels)
        marker_rms, _ = measured_rms(motion.fitted_markers, np.asarray(work.positions)[:, column])
        return dataclasses.replace(motion, marker_rms=marker_rms, lowpass_hz=low.cutoff_hz[column])

    def _confirm_merges(self, prep: PreparedFit, result: SkeletonResult) -> SkeletonResult:
        """Check the label merges against the fitted skeleton; fit again if it corrected any."""
        self._more("confirm merges")
        with self.stage(prep, "confirm merges"):
            merged, mapping = confirm_merges(prep.merge_input, prep.label_mapping, result)
        info = mapping.diagnostics["skeleton"]
        if not (info["applied"] and (info["links_added"] or info["links_removed"])):
            return dataclasses.replace(result, label_mapping=mapping, timings=dict(prep.timings))
        # The corrected merge changes the markers: segment and fit again from it.
        report = dataclasses.replace(prep.cleaning, dropped={
            k: v for k, v in prep.cleaning.dropped.items() if k not in prep.label_mapping.physical_labels
        }) if prep.cleaning is not None else None  # fmt: skip
        work, report = self._clean_merged(merged, report)
        self._more("segment", *self.refit_stages, "ik")  # the motion is on: this runs only after it
        with self.stage(prep, "segment"):
            work, left_out, landmarks = self._leave_out(work)
            segmentation = dataclasses.replace(self._segment(work), left_out=left_out,
                                               still_spans=self._still_spans(work, prep.trial_bounds))
        again = dataclasses.replace(prep, trial=work, cleaning=report, label_mapping=mapping, segmentation=segmentation,
                                    landmarks=landmarks)
        return self.motion(again, self.refit(again))


def _too_few_markers(work: Trial, given: Trial, report: CleaningReport | None) -> str:
    """Why a fit has fewer than 3 markers to segment: how many the recording had, and
    what cleaning dropped (the first few markers and reasons) with what to change."""
    if given.n_markers < 3:
        return f"the recording has {given.n_markers} marker{'' if given.n_markers == 1 else 's'}; " \
            "a skeleton needs at least 3"
    text = f"only {work.n_markers} of the recording's {given.n_markers} markers remain after cleaning; " \
        "a skeleton needs at least 3"
    dropped = dict(report.dropped) if report is not None else {}
    if not dropped:
        return text
    shown = "; ".join(f"{label}: {why}" for label, why in list(dropped.items())[:3])
    more = f" and {len(dropped) - 3} more" if len(dropped) > 3 else ""
    text += f". Cleaning dropped {len(dropped)} ({shown}{more})"
    if any("min_run_s" in why for why in dropped.values()):
        text += (f". The recording is {given.duration:.2f} s long: give a shorter min_run_s (FitOptions(clean="
                 "CleanOptions(min_run_s=...)), --min-run-s), or fit a longer recording")
    return text
