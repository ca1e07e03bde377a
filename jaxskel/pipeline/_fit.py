"""`fit_skeleton`: the whole chain from raw markers to an articulated skeleton.

    Trial --clean--> --[merge labels]--> --segment--> --joint costs / MST / tree joints-->
          --rigid skeleton--> --inverse kinematics--> SkeletonResult

Each stage is a public function too (:func:`jaxskel.clean.clean`,
:func:`jaxskel.relabel.merge_labels`, :func:`jaxskel.segment.segment_markers`,
:func:`jaxskel.joints.fit_topology`, :func:`jaxskel.skeleton.fit_rigid`,
:func:`jaxskel.skeleton.inverse_kinematics`); this module only sequences them, keeps
every stage's output and diagnostics, and reports progress.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from .._errors import (
    AmbiguousTreeWarning,
    DegenerateMotionError,
    DegenerateMotionWarning,
    InputError,
    NonRigidMarkerWarning,
)
from .._runtime.map_limit import release_programs_near_map_limit
from ..clean import CleaningReport, check_cutoff, clean
from ..io import Trial, median_extent
from ..joints import Topology, fit_topology, joint_costs
from ..relabel import needs_merging
from ..result import (
    SkeletonResult,
    near_tie_text,
    nonrigid_group_hint,
    nonrigid_group_texts,
    nonrigid_text,
    undetermined_lines,
    untested_text,
)
from ..segment import Segmentation, combine_trials, segment_markers
from ..segment import segment_names as default_names
from ._split_refit import fit_growing_count

__all__ = ["SkeletonResult", "fit_skeleton", "check_units", "prepare_fit", "finish_fit", "PreparedFit"]

#: Placements of a hinge's centre along its axis (``fit_skeleton(hinge_centres=...)``).
HINGE_CENTRES = ("limb_plane", "prior")

#: Joint centres handed to the rigid stage (``fit_skeleton(joint_centres=...)``).
JOINT_CENTRES = ("anchored", "per_frame")


def check_units(trial: Trial) -> None:
    """Raise :class:`InputError` when positions are clearly not in metres.

    A human or a lab linkage spans centimetres to a few metres per frame. The
    median over frames of the body's span (the same measure the file readers use
    to guess missing units, :func:`jaxskel.io.median_extent`) must lie in
    [2 cm, 40 m]; outside it the data are almost surely millimetres read as
    metres (or similar).
    """
    extent = median_extent(np.asarray(trial.positions))
    name = trial.source or "trial"
    if extent is None:
        raise InputError(f"{name}: no frame has two markers present; there is nothing to fit")
    if extent > 40.0:
        raise InputError(
            f"{name}: the markers span {extent:.0f} units; positions look like millimetres, not metres. "
            "Load files with jaxskel.load (it converts units) or divide by 1000."
        )
    if extent < 0.02:
        raise InputError(
            f"{name}: the markers span only {extent:.2g} units; positions do not look like metres "
            "(kilometres?). Convert to metres first."
        )


def _warn_unexercised(exercise: np.ndarray, joint_names: Sequence[str]) -> None:
    """A :class:`DegenerateMotionWarning` naming the joints the recording does not exercise."""
    from ..joints import MIN_EXERCISE_DEG

    still = [f"{name} ({sweep:.1f} deg)" for name, sweep in zip(joint_names, exercise) if sweep < MIN_EXERCISE_DEG]
    if still:
        warnings.warn(
            f"{len(still)} joint(s) barely move in this recording: {', '.join(still)} (RMS sweep of the "
            f"other segment's markers about the joint, below {MIN_EXERCISE_DEG:g} deg); their centres "
            "are not determined by the motion and come from the distance prior. Fit the recording "
            "together with a range-of-motion trial (fit_skeleton([rom, trial]))",
            DegenerateMotionWarning,
            stacklevel=5,  # fit_skeleton's caller (via fit_joints_and_skeleton, finish_fit)
        )


def _warn_undetermined(skeleton: Any, names: Sequence[str]) -> None:
    """A :class:`DegenerateMotionWarning` naming the joints the recording fixes only loosely
    (:func:`jaxskel.joints.undetermined_joints`) and the motion each lacks."""
    from ..joints import undetermined_joints

    loose = undetermined_joints(skeleton)
    if loose:
        text = undetermined_lines([u.joint for u in loose], names, skeleton)
        warnings.warn(
            f"{len(loose)} joint(s) " + "\n".join(text),
            DegenerateMotionWarning,
            stacklevel=5,  # fit_skeleton's caller (via fit_joints_and_skeleton, finish_fit)
        )


def _warn_nonrigid_groups(seg: Segmentation, names: Sequence[str]) -> None:
    """A :class:`NonRigidMarkerWarning` naming the segments whose groups are not rigid."""
    groups = nonrigid_group_texts(seg, names)
    if groups:
        warnings.warn(
            f"{len(groups)} segment(s) not rigid:\n" + "\n".join(groups) + "\n" + nonrigid_group_hint(seg),
            NonRigidMarkerWarning,
            stacklevel=5,  # fit_skeleton's caller (via fit_joints_and_skeleton, finish_fit)
        )


def _require_one_tree(topology: Topology, segmentation: Segmentation, names: Sequence[str]) -> None:
    """Raise when the joint-cost graph left a forest: the rigid skeleton and IK need one tree.

    Infeasible pairs (too few markers together, never seen together, a joint never
    exercised) have infinite cost, so segments whose every pair is infeasible stay apart.
    """
    n_seg = segmentation.n_segments
    if len(topology.edges) == n_seg - 1:
        return
    component = np.arange(n_seg)
    for a, b in np.asarray(topology.edges):  # union of the tree's edges, smallest label wins
        ca, cb = component[a], component[b]
        component[component == max(ca, cb)] = min(ca, cb)
    sizes = np.bincount(segmentation.marker_segment[segmentation.marker_segment >= 0], minlength=n_seg)
    weight = np.bincount(component, weights=sizes, minlength=n_seg)
    main = int(np.argmax(weight))
    apart = [s for s in range(n_seg) if component[s] != main]
    shown = ", ".join(f"{names[s]} ({int(sizes[s])} marker{'s' if sizes[s] != 1 else ''})" for s in apart[:8])
    more = f" and {len(apart) - 8} more" if len(apart) > 8 else ""
    reason = next((why for pair, why in topology.pair_costs.reasons.items() if set(pair) & set(apart)), "")
    raise DegenerateMotionError(
        f"no joint can be fitted between {len(apart)} of the {n_seg} segments and the rest, so there is "
        f"no single skeleton tree: {shown}{more}. Their pairs are infeasible (e.g. {reason}; all in "
        "topology.pair_costs.reasons). Fit with rigid=False to inspect the segmentation and joints, give "
        "n_segments, drop markers that are seldom seen (Trial.drop_markers), or add frames in which they "
        "are seen together with their neighbours"
    )


def _warn_untested(untested: list, names: Sequence[str], sizes: np.ndarray) -> None:
    """A :class:`DegenerateMotionWarning` naming attachments the joint costs could not test."""
    if untested:
        warnings.warn(
            "the tree may attach sparsely marked segments to the wrong neighbour:\n"
            + "\n".join(untested_text(u, names, sizes) for u in untested),
            DegenerateMotionWarning,
            stacklevel=5,  # fit_skeleton's caller (via fit_joints_and_skeleton, finish_fit)
        )


def _warn_near_ties(ties: list, names: Sequence[str]) -> None:
    """An :class:`AmbiguousTreeWarning` naming the tree joints the costs cannot tell from a rival."""
    if ties:
        warnings.warn(
            f"{len(ties)} joint(s) of the tree are not settled by the data:\n"
            + "\n".join(near_tie_text(t, names) for t in ties)
            + "\nCheck them (summary, --plot), or fit with a trial that exercises those joints",
            AmbiguousTreeWarning,
            stacklevel=5,  # fit_skeleton's caller (via fit_joints_and_skeleton, finish_fit)
        )


def _as_trials(trial_or_trials: Trial | Sequence[Trial]) -> list[Trial]:
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


def fit_skeleton(
    trial_or_trials: Trial | Sequence[Trial],
    n_segments: int | None = None,
    *,
    root: int | str | None = None,
    clean_data: bool = True,
    merge_labels: bool | str = "auto",
    alpha: float = 1e-5,
    alpha_tree: float | str = "auto",
    method: str = "lm",
    topology_frames: int = 300,
    rigid: bool = True,
    ik: bool = True,
    segment_names: Sequence[str] | None = None,
    seed: int = 0,
    progress: bool = False,
    clean_kwargs: dict[str, Any] | None = None,
    segment_kwargs: dict[str, Any] | None = None,
    confirm_merges: bool = True,
    hinge_centres: str = "limb_plane",
    joint_centres: str = "anchored",
    ik_lowpass: float | str | None = "auto",
    pose_check: bool = True,
) -> SkeletonResult:
    """Fit an articulated skeleton to marker trajectories (Kirk et al. 2005).

    Parameters
    ----------
    trial_or_trials
        One :class:`Trial`, or several trials of one subject with one marker set
        (fitted together: e.g. a range-of-motion trial plus a walk).
    n_segments
        Number of rigid segments, or ``None`` for an automatic count: the eigengap's,
        grown until every group is rigid (:func:`jaxskel.segment.segment_markers`), and grown
        again by one, with the fit rerun, while a segment holds two or more markers the
        rigid skeleton cannot hold (:mod:`jaxskel.pipeline._split_refit`; kept only if fewer
        markers are flagged). A given count is never changed.
    root
        Root segment index or a marker label on it; default the tree's centre.
    clean_data
        Run :func:`jaxskel.clean.clean` first (recommended for raw data).
    merge_labels
        Merge relabelled passive markers (:func:`jaxskel.relabel.merge_labels`): ``True``,
        ``False``, or ``"auto"``: merge when there are more labels than the most
        markers seen in any one frame *and* the recording has unnamed (``*N``)
        trajectories. A named recording with occlusions also has more labels than
        markers per frame; merging it by default would risk joining distinct
        markers, so it only gets a warning.
    alpha, alpha_tree, method, topology_frames
        Joint solve settings (see :func:`jaxskel.joints.joint_costs`, :func:`jaxskel.joints.fit_topology`).
    rigid, ik
        Also fit the rigid skeleton and run inverse kinematics.
    segment_names
        Names for the segments (length S); default: readable names from their markers'
        labels (:mod:`jaxskel.segment._names`). Display only.
    progress
        Show a progress bar over the stages.
    confirm_merges
        After merging labels, check the merges against the fitted skeleton
        (:func:`jaxskel.relabel.confirm_merges`) and, if it corrects any, segment and fit
        again from the corrected merge. Needs ``rigid`` and ``ik``.
    hinge_centres
        Where the rigid skeleton puts a joint whose centre the markers leave free along
        an axis (``topology.undetermined > 0``: knees, elbows): ``"limb_plane"`` (default)
        in the plane of its neighbouring joints (:mod:`jaxskel.skeleton._hinge_centres`), or
        ``"prior"``: where the distance prior of the joint solve left it (the paper; it
        pulls the centre out to the markers on the skin).
    joint_centres
        The joint centres the rigid skeleton is pinned to: ``"anchored"`` (default) refits
        each joint with its centre fixed in the frame of one of its segments and moves it
        along the directions that fit resolves (:mod:`jaxskel.joints._anchored_centres`; it
        corrects centres that slide along the normal of nearly coplanar markers, such as
        hips next to four waist markers: CMU 02_05 left thigh +83 -> -2 mm, HDM05 dg
        right thigh +122 -> +7 mm against the ``.asf``), or ``"per_frame"``: the joint
        solve's free centre per frame (the paper). The refit is reported in
        ``skeleton.diagnostics["anchored"]``, and its resolutions say how well the
        recording fixes each joint and bone (:meth:`SkeletonResult.joint_resolutions`,
        :meth:`SkeletonResult.undetermined_joints`; ``"per_frame"`` has none, NaN).
    ik_lowpass
        Low-pass filter of the markers the IK poses (:func:`jaxskel.clean.lowpass_markers`;
        the skeleton is fitted to the markers as measured): ``"auto"`` (default), a
        cutoff for each marker by residual analysis against its own white noise, which
        leaves noiseless or fast markers as they are; a frequency in Hz for every
        marker; or ``None``, no filter. The cutoffs are in ``motion.lowpass_hz``.
    pose_check
        Check the tree's joints between segments of three or more markers as points
        fixed in both segments' poses, and exchange the ones the poses reject
        (:mod:`jaxskel.joints._pose_check`, ``topology.pose_exchanges``, ``pose check:`` in the
        summary; CMU 02_05's head from an arm to the thorax). ``False``: the minimum
        spanning tree of the joint costs as the paper has it.
    """
    check_cutoff(ik_lowpass, allow_none=True)
    if hinge_centres not in HINGE_CENTRES:
        raise InputError(f"hinge_centres must be one of {HINGE_CENTRES}, got {hinge_centres!r}")
    if joint_centres not in JOINT_CENTRES:
        raise InputError(f"joint_centres must be one of {JOINT_CENTRES}, got {joint_centres!r}")
    release_programs_near_map_limit(stacklevel=2)  # a long-lived process: XLA crashes past the limit
    settings = dict(
        n_segments=n_segments, root=root, clean_data=clean_data, merge_labels=merge_labels,
        alpha=alpha, alpha_tree=alpha_tree, method=method, topology_frames=topology_frames,
        rigid=rigid, ik=ik, seed=seed, confirm_merges=confirm_merges, hinge_centres=hinge_centres,
        joint_centres=joint_centres, ik_lowpass=ik_lowpass, pose_check=bool(pose_check),
    )
    stages = ["clean", "merge labels", "segment", "joint costs", "tree joints", "rigid", "ik"]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(stages), desc="fit_skeleton", unit="stage")

    def on_stage(name: str) -> None:
        if bar is not None:
            bar.set_postfix_str(name)
            bar.update(1)

    prep = prepare_fit(
        trial_or_trials, n_segments, clean_data=clean_data, merge_labels=merge_labels, seed=seed,
        clean_kwargs=clean_kwargs, segment_kwargs=segment_kwargs, settings=settings, on_stage=on_stage,
    )

    check_cutoff(ik_lowpass, rate=prep.trial.rate, allow_none=True)  # the Nyquist frequency is known now
    joints_and_skeleton = functools.partial(
        fit_joints_and_skeleton, alpha=alpha, alpha_tree=alpha_tree, method=method, root=root,
        topology_frames=topology_frames, segment_names=segment_names, on_stage=on_stage,
    )
    result = fit_growing_count(
        prep, joints_and_skeleton, joints_and_skeleton, functools.partial(add_motion, on_stage=on_stage),
        seed=seed, segment_kwargs=segment_kwargs, on_stage=on_stage, stacklevel=2,
    )
    if confirm_merges and prep.label_mapping is not None and result.motion is not None:
        result = _confirm_merges_and_refit(
            prep, result, joints_and_skeleton,
            min_run_s=dict(clean_kwargs or {}).get("min_run_s", 0.5) if clean_data else None,
            n_segments=n_segments, seed=seed, segment_kwargs=segment_kwargs, on_stage=on_stage,
        )  # fmt: skip
    if bar is not None:
        bar.close()
    return result


@dataclasses.dataclass
class PreparedFit:
    """A fit after the host-side stages (clean, merge labels, segment).

    The state :func:`jaxskel.fit_batch` carries between its stages; the joint
    costs and tree joints of several prepared fits are solved together.
    """

    input_labels: tuple[str, ...]
    trial: Trial
    cleaning: CleaningReport | None
    label_mapping: Any
    segmentation: Segmentation
    trial_bounds: tuple[tuple[int, int], ...]
    timings: dict[str, float]
    settings: dict[str, Any]
    #: The cleaned trial given to merge_labels (``None`` without merging): the
    #: skeleton's confirmation of the merges starts again from it.
    merge_input: Trial | None = None

    @contextlib.contextmanager
    def stage(self, name: str, on_stage: Any = None):
        """Time a stage into ``timings`` (seconds) and report it to ``on_stage(name)``."""
        t0 = time.perf_counter()
        yield
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        if on_stage is not None:
            on_stage(name)


def prepare_fit(
    trial_or_trials: Trial | Sequence[Trial],
    n_segments: int | None = None,
    *,
    clean_data: bool = True,
    merge_labels: bool | str = "auto",
    seed: int = 0,
    clean_kwargs: dict[str, Any] | None = None,
    segment_kwargs: dict[str, Any] | None = None,
    settings: dict[str, Any] | None = None,
    on_stage: Any = None,
    device_lock: Any = None,
) -> PreparedFit:
    """The host-side stages of :func:`fit_skeleton`: check units, clean, merge labels, segment.

    ``device_lock`` (a lock) is held around the stages that run JAX code (label
    merging, segmentation), so that other threads may run the numpy-only ones.
    """
    device = device_lock if device_lock is not None else contextlib.nullcontext()
    trials = _as_trials(trial_or_trials)
    for t in trials:
        check_units(t)
    combined = combine_trials(trials)
    bounds = tuple(combined.metadata.get("trial_bounds", ((0, combined.n_frames),)))
    prep = PreparedFit(
        input_labels=combined.labels, trial=combined, cleaning=None, label_mapping=None,
        segmentation=None, trial_bounds=bounds, timings={}, settings=dict(settings or {}),  # type: ignore[arg-type]
    )
    work = combined

    # Decide on label merging from the raw data: cleaning's short-run rule would
    # otherwise drop the short relabelled fragments before they can be merged.
    if merge_labels == "auto":
        do_merge = needs_merging(work) and any(lab.startswith("*") for lab in work.labels)
        if needs_merging(work) and not do_merge:
            warnings.warn(
                "this recording has more labels than markers in any frame, but its labels are named, "
                "so labels were not merged; pass merge_labels=True (CLI: --merge-labels yes) if it "
                "comes from a passive system that relabels markers after occlusions",
                DegenerateMotionWarning,
                stacklevel=3,
            )
    elif isinstance(merge_labels, bool):
        do_merge = merge_labels
    else:
        raise InputError(f"merge_labels must be True, False or 'auto', got {merge_labels!r}")
    clean_options = dict(clean_kwargs or {})
    min_run_s = clean_options.pop("min_run_s", 0.5)

    report = None
    with prep.stage("clean", on_stage):
        if clean_data:
            work, report = clean(work, min_run_s=0.0 if do_merge else min_run_s, **clean_options)

    mapping = None
    with prep.stage("merge labels", on_stage), device:
        if do_merge:
            from ..relabel import merge_labels as _merge

            prep.merge_input = work
            work, mapping = _merge(work)
            work, report = _clean_merged(work, report, min_run_s if clean_data else None)

    with prep.stage("segment", on_stage), device:
        segmentation = _segment(work, n_segments, seed, segment_kwargs)
    prep.trial, prep.cleaning, prep.label_mapping, prep.segmentation = work, report, mapping, segmentation
    return prep


def _clean_merged(work: Trial, report: CleaningReport | None, min_run_s: float | None) -> tuple[Trial, Any]:
    """After merging labels: drop physical markers that are still short-lived (``None``: keep all)."""
    if min_run_s is None:
        return work, report
    work, after = clean(work, trim_s=0.0, reject_jumps=False, min_run_s=min_run_s)
    return work, dataclasses.replace(
        report, dropped={**report.dropped, **after.dropped}, duplicates={**report.duplicates, **after.duplicates}
    )


def _segment(work: Trial, n_segments: int | None, seed: int, segment_kwargs: dict[str, Any] | None) -> Segmentation:
    if work.n_markers < 3:
        raise DegenerateMotionError(
            f"only {work.n_markers} markers remain after cleaning; a skeleton needs at least 3 "
            "(see result.cleaning / the cleaning report for what was dropped)"
        )
    return segment_markers(work, n_segments, seed=seed, **(segment_kwargs or {}))


def fit_joints_and_skeleton(
    prep: PreparedFit,
    *,
    alpha: float,
    alpha_tree: float | str,
    method: str,
    root: int | str | None,
    topology_frames: int,
    segment_names: Sequence[str] | None = None,
    on_stage: Any = None,
) -> SkeletonResult:
    """The stages of :func:`fit_skeleton` after segmentation, for one prepared fit:
    all-pairs joint costs, MST + tree joints on all frames, then :func:`finish_fit`."""
    with prep.stage("joint costs", on_stage):
        pairs = joint_costs(prep.trial, prep.segmentation, alpha=alpha, max_frames=topology_frames, method=method)
    with prep.stage("tree joints", on_stage):
        topology = fit_topology(
            prep.trial, prep.segmentation, pairs, root=root, alpha=alpha, alpha_tree=alpha_tree, method=method,
            pose_check=prep.settings.get("pose_check", True),
        )
    return finish_fit(prep, topology, segment_names=segment_names, on_stage=on_stage)


def _inverse_kinematics(prep: PreparedFit, skeleton: Any, work: Trial, on_stage: Any) -> Any:
    """The IK stage: the skeleton's motion over ``work``, or ``None`` (no skeleton, or ``ik=False``)."""
    with prep.stage("ik", on_stage):
        if not (prep.settings.get("ik", True) and skeleton is not None):
            return None
        from ..skeleton import inverse_kinematics, solver_shape

        # the refinement's slot count: its compiled solver serves the IK too
        slots, _ = solver_shape(skeleton.marker_segment, skeleton.edges, skeleton.marker_segment.shape[0])
        cutoff = prep.settings.get("ik_lowpass", "auto")
        if cutoff is None:
            return inverse_kinematics(skeleton, work, slots=slots)
        from ..clean import lowpass_markers

        # IK poses every frame on its own: the markers' white noise is filtered out first
        low = lowpass_markers(work, cutoff)
        motion = inverse_kinematics(skeleton, low.trial, slots=slots)
        # the residual is reported against the markers as measured, not as filtered
        column = work.marker_index(motion.marker_labels)
        raw = np.asarray(work.positions)[:, column]
        miss = np.sum((motion.fitted_markers - raw) ** 2, axis=-1)
        seen = np.isfinite(miss)
        marker_rms = np.sqrt(np.where(seen, miss, 0.0).sum(1) / np.maximum(seen.sum(1), 1))
        return dataclasses.replace(motion, marker_rms=marker_rms, lowpass_hz=low.cutoff_hz[column])


def add_motion(prep: PreparedFit, result: SkeletonResult, on_stage: Any = None) -> SkeletonResult:
    """``result`` (fitted without IK) with the IK stage run as ``prep.settings`` ask."""
    motion = _inverse_kinematics(prep, result.skeleton, result.trial, on_stage)
    return dataclasses.replace(result, motion=motion, timings=dict(prep.timings))


def _confirm_merges_and_refit(
    prep: PreparedFit,
    result: SkeletonResult,
    refit: Any,
    *,
    min_run_s: float | None,
    n_segments: int | None,
    seed: int,
    segment_kwargs: dict[str, Any] | None,
    on_stage: Any = None,
) -> SkeletonResult:
    """Check the label merges against the fitted skeleton; fit again if it corrected any.

    ``refit(prep)`` runs the joint and skeleton stages on a prepared fit.
    """
    from ..relabel import confirm_merges

    with prep.stage("confirm merges", on_stage):
        merged, mapping = confirm_merges(prep.merge_input, prep.label_mapping, result)
    info = mapping.diagnostics["skeleton"]
    if not (info["applied"] and (info["links_added"] or info["links_removed"])):
        return dataclasses.replace(result, label_mapping=mapping, timings=dict(prep.timings))
    # The corrected merge changes the markers: segment and fit again from it.
    report = dataclasses.replace(prep.cleaning, dropped={
        k: v for k, v in prep.cleaning.dropped.items() if k not in prep.label_mapping.physical_labels
    }) if prep.cleaning is not None else None  # fmt: skip
    work, report = _clean_merged(merged, report, min_run_s)
    with prep.stage("segment", on_stage):
        segmentation = _segment(work, n_segments, seed, segment_kwargs)
    again = dataclasses.replace(prep, trial=work, cleaning=report, label_mapping=mapping, segmentation=segmentation)
    return refit(again)


def finish_fit(
    prep: PreparedFit,
    topology: Topology,
    *,
    segment_names: Sequence[str] | None = None,
    on_stage: Any = None,
) -> SkeletonResult:
    """The stages of :func:`fit_skeleton` after the tree joints: rigid skeleton and IK."""
    segmentation, work = prep.segmentation, prep.trial
    names = tuple(segment_names) if segment_names is not None else default_names(segmentation.groups)
    if len(names) != segmentation.n_segments:
        raise InputError(
            f"segment_names has {len(names)} names for {segmentation.n_segments} segments"
        )

    from ..joints import untested_joints

    _warn_nonrigid_groups(segmentation, names)
    _warn_untested(untested_joints(segmentation, topology), names, segmentation.segment_sizes)
    from ..joints import near_ties

    _warn_near_ties(near_ties(work, segmentation, topology), names)
    skeleton = None
    if prep.settings.get("rigid", True) and len(topology.edges):
        _require_one_tree(topology, segmentation, names)
    with prep.stage("rigid", on_stage):
        if prep.settings.get("rigid", True) and len(topology.edges):
            from ..skeleton import SOLVED_JOINT_WEIGHT, fit_rigid

            sliding = None
            if prep.settings.get("hinge_centres", "limb_plane") == "limb_plane":
                sliding = np.asarray(topology.undetermined) > 0
            centres, anchored = topology.joint_positions, None
            if prep.settings.get("joint_centres", "anchored") == "anchored":
                from ..joints import anchored_centres

                x, mask = work.to_arrays()
                anchored = anchored_centres(
                    x, mask, segmentation.marker_segment, topology.edges, topology.joint_positions
                )
                centres = anchored.joint_positions
            skeleton = fit_rigid(
                work, segmentation.marker_segment, topology.edges, centres, root=topology.root,
                sliding_joints=sliding, joint_weight=SOLVED_JOINT_WEIGHT,
            )
            if anchored is not None:
                report = {k: v for k, v in vars(anchored).items() if k != "joint_positions"}
                skeleton = dataclasses.replace(skeleton, diagnostics={**skeleton.diagnostics, "anchored": report})
                joint_names = [f"{names[p]}-{names[c]}" for p, c in topology.edges]
                _warn_unexercised(anchored.exercise, joint_names)
                _warn_undetermined(skeleton, names)
            nonrigid = nonrigid_text(skeleton, names, segmentation.n_segments)
            if nonrigid is not None:
                warnings.warn(f"markers {nonrigid}", NonRigidMarkerWarning, stacklevel=4)
    # without IK (a fit that may be segmented again first, :mod:`jaxskel.pipeline._split_refit`) the
    # stage is left to :func:`add_motion`
    motion = _inverse_kinematics(prep, skeleton, work, on_stage) if prep.settings.get("ik", True) else None
    return SkeletonResult(
        input_labels=prep.input_labels,
        trial=work,
        cleaning=prep.cleaning,
        label_mapping=prep.label_mapping,
        segmentation=segmentation,
        topology=topology,
        skeleton=skeleton,
        motion=motion,
        segment_names=names,
        trial_bounds=prep.trial_bounds,
        timings=dict(prep.timings),
        settings=dict(prep.settings),
    )
