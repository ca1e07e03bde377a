"""`track`: calibrate once, track many: pose new trials on a saved skeleton.

A subject is fitted once (``jaxskel fit CAL.c3d -o subject.h5``); every later trial is
posed on that skeleton by inverse kinematics alone, with no segmentation, joint search or
rigid fit, so all takes share one rig, bone lengths to the bit.

Per trial (host side, numpy): read, check the units, clean (:func:`jaxskel.clean.clean`,
the fit's cleaning settings), match its markers to the skeleton's by label
(:func:`match_markers`), low-pass filter them as the fit's IK does
(:func:`jaxskel.clean.lowpass_markers`). Then the trials of a group (up to ``batch_size``
trials, at most :data:`GROUP_FRAMES` frames) are concatenated along time and posed by
**one** batched IK solve (:func:`jaxskel.skeleton.inverse_kinematics`, frames vectorised,
gaps filled from each trial's own frames only), with the solver layout of the fit's
(:func:`jaxskel.skeleton.solver_shape`), so a process that fitted, or a warm compile cache,
compiles nothing new. Each trial's motion is then cut out, its residual taken against the
markers as measured, and the frames where a segment cannot be posed marked
(:func:`posed_segments`).

What a trial may lack: markers of the skeleton (tracked without them; reported), a marker
for part of the trial (gap-filled), markers the skeleton does not know (ignored;
reported), subject prefixes or another letter case in its labels (matched; reported).
A segment the trial's markers cannot place in some frames is reported unposed there, by
name, and its fitted markers are NaN there. A trial with fewer than three of the
skeleton's markers fails with a message naming what it lacks; the other trials go on.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import ConvergenceWarning, InputError, JaxskelError, TrackingWarning
from .._math.frames import cut_frames
from .._runtime.precision import float64_scope
from ..clean import clean, lowpass_markers
from ..io import Trial, check_load_arguments, check_output, refuse_input
from ..anatomy import Anatomy
from ..result import TrackedTrial, angles_or_none, load_anatomy, load_angles, load_skeleton, write_angles_sto
from ..skeleton import Skeleton, inverse_kinematics, measured_rms, segment_members, solver_shape
from ._batch import BatchResult
from ._local import Item, TrialOutcome, failed
from ._options import FitOptions
from ._plan import check_units
from ._trial_warnings import Caught, emit

__all__ = ["TRACK_GROUPS", "MarkerMatch", "match_markers", "posable_segments", "posed_segments", "track",
           "track_settings"]

#: The settings groups of :class:`FitOptions` that tracking uses (the others are the fit's).
TRACK_GROUPS = ("clean", "motion")

#: Most frames one batched IK solve poses (a group of trials is cut there): bounds the
#: host memory of a solve (about 2 kB per frame and marker slot).
GROUP_FRAMES = 200_000

#: What a tracked trial writes next to its result file, by ``track``'s flag: its suffix and
#: its kind (:data:`jaxskel.io._output_check.OUTPUT_KINDS`).
EXPORTS = {"bvh": (".bvh", "bvh"), "trc": (".trc", "trc"), "angles": (".sto", "sto")}


# ------------------------------------------------------------------ markers
@dataclasses.dataclass(frozen=True)
class MarkerMatch:
    """The skeleton's markers found in a trial.

    ``columns`` (M,) is each skeleton marker's column in the trial (-1: the trial lacks
    it); ``matched`` maps a skeleton label to the trial label it was matched to where the
    two differ; ``extra`` are the trial's labels no skeleton marker took.
    """

    columns: np.ndarray
    missing: tuple[str, ...]
    extra: tuple[str, ...]
    matched: dict[str, str]


def _bare(label: str) -> str:
    """A label without its subject prefix (``"Subject:LKNE"`` -> ``"LKNE"``) or outer spaces."""
    return label.rpartition(":")[2].strip()


def match_markers(skeleton_labels: Sequence[str], trial_labels: Sequence[str]) -> MarkerMatch:
    """Match the skeleton's markers to a trial's by label.

    In turn: equal labels; equal after dropping a subject prefix (``Subject:LKNE``) on
    either side; equal ignoring letter case, where that is unambiguous. Each trial label
    is taken at most once.
    """
    trial_labels = [str(v) for v in trial_labels]
    columns = np.full(len(skeleton_labels), -1, dtype=np.int64)
    free = dict.fromkeys(range(len(trial_labels)))

    def take(key: Callable[[str], str]) -> None:
        table: dict[str, list[int]] = {}
        for i in free:
            table.setdefault(key(trial_labels[i]), []).append(i)
        for m, lab in enumerate(skeleton_labels):
            hits = table.get(key(lab), []) if columns[m] < 0 else []
            hits = [i for i in hits if i in free]
            if len(hits) == 1:
                columns[m] = hits[0]
                free.pop(hits[0])

    take(lambda s: s)
    take(_bare)
    take(lambda s: _bare(s).casefold())
    matched = {lab: trial_labels[c] for lab, c in zip(skeleton_labels, columns.tolist()) if c >= 0
               and trial_labels[c] != lab}
    return MarkerMatch(
        columns=columns,
        missing=tuple(lab for lab, c in zip(skeleton_labels, columns.tolist()) if c < 0),
        extra=tuple(trial_labels[i] for i in free),
        matched=matched,
    )


# ------------------------------------------------------------------ posing
def posable_segments(skeleton: Skeleton, visible: np.ndarray) -> np.ndarray:
    """(F, S): the frames' visible markers (``visible`` (F, M)) fix the segment's pose.

    A segment with ``n`` markers is fixed when ``min(3, n)`` of them are seen (what the fit
    itself poses it from), or when at least one is seen and, with the joints it shares
    with its neighbours, they make three points.
    """
    member = segment_members(skeleton)
    n_markers = member.sum(axis=0)
    degree = np.bincount(np.asarray(skeleton.edges).ravel(), minlength=skeleton.n_segments)
    seen = np.asarray(visible, bool).astype(np.int64) @ member.astype(np.int64)
    enough = (n_markers > 0) & (seen >= np.minimum(3, n_markers))
    return enough | ((seen >= 1) & (seen + degree >= 3))


def posed_segments(posable: np.ndarray) -> np.ndarray:
    """(F, S) of one trial: posable, or inside a gap between posable frames (which the IK fills).

    Before a segment's first posable frame and after its last, the trial does not say
    where it is: not posed."""
    posable = np.asarray(posable, bool)
    after_first = np.cumsum(posable, axis=0) > 0
    before_last = np.cumsum(posable[::-1], axis=0)[::-1] > 0
    return after_first & before_last


# ------------------------------------------------------------------ one trial
@dataclasses.dataclass
class _Prepared:
    """A trial ready for the group solve."""

    item: Item
    trial: Trial  # cleaned, in the skeleton's marker order: its positions as measured (NaN missing)
    filtered: np.ndarray  # (F, M, 3) what the IK poses (NaN missing)
    lowpass_hz: np.ndarray | None
    input_labels: tuple[str, ...]
    match: MarkerMatch
    dropped: dict[str, str]
    cleaning: Any
    caught: list[Caught]
    timings: dict[str, float]


def _trial_name(value: Any, index: int) -> str:
    if isinstance(value, (str, os.PathLike)):
        return Path(value).stem
    stem = Path(str(value.metadata.get("file") or value.source or "")).stem
    return stem or f"trial{index + 1}"


def _listed(labels: Sequence[str], most: int = 8) -> str:
    shown = ", ".join(labels[:most])
    return shown + (f" and {len(labels) - most} more" if len(labels) > most else "")


def _prepare(item: Item, skeleton: Skeleton, options: FitOptions) -> _Prepared:
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        trial = item.trials()[0]
        loaded = tuple(trial.labels)
        timings["read"] = time.perf_counter() - t0
        check_units(trial)
        labels = tuple(skeleton.marker_labels)
        match = match_markers(labels, trial.labels)
        if (match.columns >= 0).sum() < 3:
            raise InputError(
                f"{item.name} has {int((match.columns >= 0).sum())} of the skeleton's {len(labels)} markers; "
                f"at least 3 are needed to pose it. The skeleton's markers: {_listed(list(labels))}; the trial's: "
                f"{_listed(list(trial.labels))}. Track trials recorded with the calibration's marker set"
            )
        t1 = time.perf_counter()
        report, dropped = None, {}
        if options.clean.enabled:
            trial, report = clean(trial, **options.clean.kwargs())
            dropped = dict(report.dropped)
        timings["clean"] = time.perf_counter() - t1
        column = {lab: i for i, lab in enumerate(trial.labels)}
        raw = np.full((trial.n_frames, len(labels), 3), np.nan)
        source = [match.matched.get(lab, lab) if c >= 0 else None for lab, c in zip(labels, match.columns.tolist())]
        for m, lab in enumerate(source):
            if lab is not None and lab in column:
                raw[:, m] = trial.positions[:, column[lab]]
        seen = np.isfinite(raw).all(axis=-1).any(axis=0)  # the skeleton's markers with data
        kept = int(seen.sum())
        if kept < 3:
            raise InputError(
                f"{item.name}: after cleaning, {kept} of the skeleton's markers have data ("
                + "; ".join(f"{lab}: {why}" for lab, why in list(dropped.items())[:8])
                + "); at least 3 are needed: check the recording, or track with --no-clean"
            )
        ordered = Trial(positions=raw, labels=labels, rate=trial.rate, up_axis=trial.up_axis, source=trial.source,
                        metadata=dict(trial.metadata))
        t2 = time.perf_counter()
        cutoff = options.motion.lowpass
        filtered, lowpass_hz = raw, None
        if cutoff is not None:
            low = lowpass_markers(ordered.select_markers(np.flatnonzero(seen)), cutoff)
            filtered = raw.copy()
            filtered[:, seen] = low.trial.positions
            lowpass_hz = np.full(len(labels), np.nan)
            lowpass_hz[seen] = low.cutoff_hz
        timings["lowpass"] = time.perf_counter() - t2
    caught = list(dict.fromkeys((w.category, str(w.message)) for w in got))
    lost = {lab: dropped[src] for lab, src in zip(labels, source) if src is not None and src in dropped}
    return _Prepared(item, ordered, filtered, lowpass_hz, loaded, match, lost, report, caught, timings)


def _finish(prep: _Prepared, skeleton: Skeleton, motion: Any, calibration: Calibration, settings: dict[str, Any],
            ik_seconds: float) -> tuple[TrackedTrial, list[Caught]]:
    """The trial's TrackedTrial from its cut of the group's motion, and its warnings."""
    measured = np.asarray(prep.trial.positions)
    visible = np.isfinite(measured).all(axis=-1)
    posed = posed_segments(posable_segments(skeleton, visible))
    member = segment_members(skeleton)
    marker_posed = (posed.astype(np.int64) @ member.T.astype(np.int64)) > 0  # (F, M)
    fitted = np.where(marker_posed[..., None], motion.fitted_markers, np.nan)
    rms, n_seen = measured_rms(fitted, measured)
    rms = np.where(n_seen > 0, rms, np.nan)
    motion = dataclasses.replace(motion, fitted_markers=fitted, marker_rms=rms, lowpass_hz=prep.lowpass_hz,
                                 rate=prep.trial.rate, converged=bool((motion.result == 0).all()))
    tracked = TrackedTrial(
        name=prep.item.name, trial=prep.trial, input_labels=prep.input_labels, skeleton=skeleton, motion=motion,
        segment_posed=posed, missing_markers=prep.match.missing + tuple(prep.dropped),
        extra_markers=prep.match.extra, matched=dict(prep.match.matched), cleaning=prep.cleaning,
        calibration=calibration.path, anatomy=calibration.anatomy, angle_frames=calibration.angle_frames,
        timings={**prep.timings, "ik": ik_seconds},
        settings=settings,
    )
    caught = list(prep.caught)
    if prep.match.missing or prep.dropped:
        parts = []
        if prep.match.missing:
            parts.append(f"the trial lacks {len(prep.match.missing)} of the skeleton's markers "
                         f"({_listed(list(prep.match.missing))})")
        if prep.dropped:
            parts.append("cleaning dropped " + "; ".join(f"{lab} ({why})" for lab, why in prep.dropped.items()))
        caught.append((TrackingWarning, "; ".join(parts) + ": tracked with the others"))
    unposed = tracked.unposed_segments()
    if unposed:
        lacking = []
        for s, name in enumerate(skeleton.names()):
            if name in unposed:
                gone = [lab for m, lab in enumerate(skeleton.marker_labels) if member[m, s] and not visible[:, m].any()]
                frames = "all" if unposed[name] == tracked.n_frames else unposed[name]
                lacking.append(f"{name} ({frames} frames" + (f"; no data for {_listed(gone, 4)}" if gone else "") + ")")
        caught.append((TrackingWarning, "too few markers to pose segment(s) " + ", ".join(lacking)
                       + ": they are marked unposed there (segment_posed), their fitted markers NaN"))
    failures = int((motion.result != 0).sum())
    if failures:
        text = (f"inverse kinematics hit its step limit in {failures} frames (motion.result == 7); check those "
                "frames for swapped or jumping markers")
        caught.append((ConvergenceWarning, text))
    return tracked, caught


# ------------------------------------------------------------------ a group
@float64_scope
def _solve_group(preps: Sequence[_Prepared], skeleton: Skeleton) -> tuple[list[Any], float]:
    """One batched IK solve of the trials of a group, cut back into one motion per trial."""
    t0 = time.perf_counter()
    x = np.concatenate([p.filtered for p in preps])
    bounds, start = [], 0
    for p in preps:
        bounds.append((start, start + p.trial.n_frames))
        start += p.trial.n_frames
    slots, _ = solver_shape(skeleton.marker_segment, skeleton.edges, len(skeleton.marker_labels))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # said per trial (_finish)
        motion = inverse_kinematics(skeleton, (x, np.isfinite(x).all(axis=-1)), trial_bounds=bounds, slots=slots)
    cuts = [cut_frames(motion, motion.n_frames, slice(lo, hi)) for lo, hi in bounds]
    return cuts, time.perf_counter() - t0


# ------------------------------------------------------------------ track
@dataclasses.dataclass(frozen=True)
class Calibration:
    """Where a tracked take's skeleton came from: its result file (``""``: given in memory),
    the body it named (``None``: none named) and its anatomical frames (``None``: no joint
    angles), which every take inherits."""

    path: str = ""
    anatomy: Anatomy | None = None
    angle_frames: np.ndarray | None = None


def _skeleton_of(skeleton: Any) -> tuple[Skeleton, Calibration]:
    if isinstance(skeleton, Skeleton):
        return skeleton, Calibration()
    if isinstance(skeleton, (str, os.PathLike)):
        angles = load_angles(skeleton)
        return load_skeleton(skeleton), Calibration(os.path.abspath(skeleton), load_anatomy(skeleton),
                                                    angles.frames if angles is not None else None)
    from ..result import SkeletonResult

    if isinstance(skeleton, SkeletonResult):
        if skeleton.skeleton is None:
            raise InputError("this result has no rigid skeleton (fitted with rigid=False); fit with the defaults")
        angles = angles_or_none(skeleton.skeleton, skeleton.motion, skeleton.anatomy)
        return skeleton.skeleton, Calibration(anatomy=skeleton.anatomy,
                                              angle_frames=angles.frames if angles is not None else None)
    raise InputError(
        f"track takes a Skeleton, a SkeletonResult or the path of a result file, got {type(skeleton).__name__}"
    )


def track_settings(options: FitOptions) -> dict[str, Any]:
    """The settings of ``options`` that tracking uses (:data:`TRACK_GROUPS`), by flat name."""
    return {info.flat: options.get(info.flat) for group, _, info, _ in FitOptions.settings() if group in TRACK_GROUPS}


def track_options(options: FitOptions | None, settings: dict[str, Any]) -> FitOptions:
    """The options of a tracking run: ``options`` (or the defaults) with ``settings``
    (flat names) changed; only the cleaning and IK settings (:data:`TRACK_GROUPS`) apply."""
    if options is not None and not isinstance(options, FitOptions):
        raise InputError(f"options must be a jaxskel.FitOptions, got {type(options).__name__}")
    options = options or FitOptions()
    where = {info.flat: group for group, _, info, _ in FitOptions.settings()}
    foreign = [k for k in settings if k in where and where[k] not in TRACK_GROUPS]
    if foreign:
        raise InputError(
            f"{', '.join(foreign)}: fit setting(s); tracking uses the saved skeleton and only the cleaning and IK "
            "settings (" + ", ".join(track_settings(options or FitOptions())) + ")"
        )
    options = options.replace(**settings)
    if not options.motion.enabled:
        raise InputError("tracking is inverse kinematics; ik=False leaves nothing to do")
    return options


def _items(trials: Any, units: str | None, up_axis: str | None) -> list[Item]:
    if isinstance(trials, (str, os.PathLike, Trial)):
        trials = [trials]
    if not isinstance(trials, Sequence) or not trials:
        raise InputError("track takes a Trial, a path, or a non-empty list of them")
    reading = tuple((k, v) for k, v in (("units", units), ("up_axis", up_axis)) if v is not None)
    items = []
    for i, value in enumerate(trials):
        if not isinstance(value, (str, os.PathLike, Trial)):
            raise InputError(f"track item {i} must be a Trial or a path, got {value!r:.80}")
        if isinstance(value, (str, os.PathLike)) and not Path(value).is_file():
            raise InputError(f"{value}: no such recording")
        items.append(Item(i, _trial_name(value, i), "", (value,), None, reading))
    return items


def _outputs(items: list[Item], outdir: Path, exports: Sequence[str], overwrite: bool, calibration: Calibration) -> list[Item]:
    """Each item with its result file ``outdir/<name>.h5``, after checking every output
    before any work: one file per name, none an input or the calibration, none an existing
    file without ``overwrite``, all writable."""
    taken: dict[str, str] = {}
    inputs = [str(v) for it in items for v in it.inputs if isinstance(v, (str, os.PathLike))]
    if calibration.path:
        inputs.append(calibration.path)
    out = []
    for it in items:
        paths = [outdir / f"{it.name}.h5"] + [outdir / f"{it.name}{EXPORTS[e][0]}" for e in exports]
        for path, kind in zip(paths, ["result", *(EXPORTS[e][1] for e in exports)]):
            key = os.path.normcase(os.path.abspath(path))
            if key in taken:
                raise InputError(
                    f"{taken[key]} and {it.inputs_text()} would both write {path} (the same file name); "
                    "rename one, or track them into different folders"
                )
            taken[key] = it.inputs_text()
            refuse_input(path, inputs, f"the output of {it.name}")
            check_output(path, kind, f"the output of {it.name},")
            if path.exists() and not overwrite:
                raise InputError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
        out.append(dataclasses.replace(it, output=paths[0]))
    return out


def _row(tracked: TrackedTrial | None, item: Item, seconds: float) -> dict[str, Any]:
    row: dict[str, Any] = {"trial": item.name, "input": item.inputs_text(), "status": "ok",
                           "seconds": round(seconds, 3)}
    if tracked is not None:
        rms = np.asarray(tracked.motion.marker_rms)
        row.update(frames=tracked.n_frames, residual_median_mm=round(1e3 * float(np.nanmedian(rms)), 3),
                   missing=" ".join(tracked.missing_markers), extra=len(tracked.extra_markers),
                   unposed=" ".join(tracked.unposed_segments()), output=str(item.output or ""))
    return row


@float64_scope
def track(
    skeleton: Any,
    trials: Any,
    outdir: str | os.PathLike[str] | None = None,
    *,
    options: FitOptions | None = None,
    bvh: bool = False,
    trc: bool = False,
    angles: bool = False,
    overwrite: bool = False,
    batch_size: int = 16,
    scheduler: Any = None,
    keep_results: bool | None = None,
    progress: bool = False,
    units: str | None = None,
    up_axis: str | None = None,
    **settings: Any,
) -> BatchResult:
    """Pose trials on a saved skeleton: calibrate once, track many (module docstring).

    Parameters
    ----------
    skeleton
        The calibration: a result file's path (``jaxskel fit CAL -o subject.h5``), a
        :class:`jaxskel.skeleton.Skeleton` or a :class:`jaxskel.SkeletonResult`.
    trials
        A :class:`jaxskel.Trial` or a recording's path, or a list of them.
    outdir
        Write ``outdir/<trial name>.h5`` per trial (the result schema, docs/result-format.md),
        and with ``bvh`` / ``trc`` the BVH on the calibration's rig and the fitted,
        gap-filled markers as TRC, with ``angles`` the anatomical joint angles as an OpenSim
        ``.sto`` (:meth:`jaxskel.TrackedTrial.joint_angles`; the calibration must have named a
        human body). Every output is checked before any work; an existing file is replaced
        only with ``overwrite``.
    options, settings
        The cleaning and IK settings (:class:`jaxskel.FitOptions` groups ``clean`` and
        ``motion``, or their flat names: ``ik_lowpass=None``); default the fit's defaults.
    batch_size
        Most trials posed by one batched IK solve.
    scheduler
        A Dask scheduler address or ``distributed.Client``: groups of trials are tracked on
        its workers (which need ``outdir``, on a file system they share).
    keep_results
        Keep each :class:`TrackedTrial` in its outcome (default: in process, yes; on Dask,
        no: the files are the results).
    progress
        A progress bar, one step per trial.
    units, up_axis
        How the recordings are read (:func:`jaxskel.load`).

    Returns
    -------
    :class:`jaxskel.pipeline.BatchResult`, one :class:`TrialOutcome` per trial in order:
    ``status`` "ok" (``result`` the :class:`jaxskel.TrackedTrial`, ``output`` its file) or
    "failed" (``error`` says why). Each trial's warnings (markers it lacks, segments it
    cannot pose) are issued naming the trial (:class:`jaxskel.TrackingWarning`).
    """
    t_start = time.perf_counter()
    check_load_arguments(units, up_axis)
    options = track_options(options, settings)
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise InputError(f"batch_size must be a positive whole number, got {batch_size!r}")
    for name, value in (("bvh", bvh), ("trc", trc), ("angles", angles), ("overwrite", overwrite),
                        ("progress", progress)):
        if not isinstance(value, bool):
            raise InputError(f"{name} must be True or False, got {value!r}")
    skel, calibration = _skeleton_of(skeleton)
    items = _items(trials, units, up_axis)
    exports = [e for e, on in (("bvh", bvh), ("trc", trc), ("angles", angles)) if on]
    if exports and outdir is None:
        raise InputError("bvh=True / trc=True / angles=True write files: give outdir")
    if angles and (calibration.anatomy is None or not calibration.anatomy.humanoid):
        raise InputError("angles=True needs a calibration that named a human body (its result has no human "
                         "/anatomy); refit the calibration with anatomy=True, the default")
    out = None
    if outdir is not None:
        out = Path(outdir)
        if out.exists() and not out.is_dir():
            raise InputError(f"{out} is a file; track writes a folder of result files: give a folder")
        items = _outputs(items, out, exports, overwrite, calibration)
    if scheduler is not None:
        if out is None:
            raise InputError("tracking on a Dask scheduler writes files: give outdir")
        if keep_results:
            raise InputError("keep_results=True needs in-process tracking (no scheduler): results stay on the workers")
    keep = (scheduler is None) if keep_results is None else bool(keep_results)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(items), desc="track", unit="trial")
    outcomes: dict[int, TrialOutcome] = {}

    def done(item: Item, outcome: TrialOutcome) -> None:
        outcomes[item.index] = outcome
        emit(item.name, outcome.warnings)
        if bar is not None:
            text = outcome.row.get("residual_median_mm")
            bar.set_postfix_str(f"{item.name}: " + (f"{text:.2f} mm" if text is not None else outcome.status))
            bar.update(1)

    try:
        if scheduler is not None:
            _track_distributed(items, skel, calibration, options, exports, overwrite, batch_size, scheduler, done)
        else:
            _track_local(items, skel, calibration, options, exports, overwrite, batch_size, keep, done)
    finally:
        if bar is not None:
            bar.close()
    return BatchResult([outcomes[it.index] for it in items], None, time.perf_counter() - t_start)


def _track_local(items: list[Item], skeleton: Skeleton, calibration: Calibration, options: FitOptions,
                 exports: Sequence[str], overwrite: bool, batch_size: int, keep: bool,
                 done: Callable[[Item, TrialOutcome], None]) -> None:
    """Track ``items`` in this process: prepare each, pose them in groups, finish and write each."""
    settings = track_settings(options)
    group: list[_Prepared] = []
    started: dict[int, float] = {}

    def solve() -> None:
        if not group:
            return
        try:
            motions, seconds = _solve_group(group, skeleton)
        except Exception as exc:  # noqa: BLE001 - a failed solve fails its group's trials only
            for p in group:
                done(p.item, failed(p.item, exc, time.perf_counter() - started[p.item.index]))
            group.clear()
            return
        total = sum(p.trial.n_frames for p in group)
        for p, motion in zip(group, motions):
            try:
                tracked, caught = _finish(p, skeleton, motion, calibration, settings,
                                          seconds * p.trial.n_frames / total)
                if p.item.output is not None:
                    _write(tracked, p.item.output, exports, overwrite)
                outcome = TrialOutcome(p.item.name, "", "ok", output=p.item.output,
                                       result=tracked if keep else None,
                                       row=_row(tracked, p.item, time.perf_counter() - started[p.item.index]),
                                       warnings=tuple(caught))
            except Exception as exc:  # noqa: BLE001 - one trial's failure is its own
                outcome = failed(p.item, exc, time.perf_counter() - started[p.item.index])
            done(p.item, outcome)
        group.clear()

    for item in items:
        started[item.index] = time.perf_counter()
        try:
            prep = _prepare(item, skeleton, options)
        except (JaxskelError, OSError) as exc:
            done(item, failed(item, exc, time.perf_counter() - started[item.index]))
            continue
        if group and (len(group) >= batch_size
                      or sum(p.trial.n_frames for p in group) + prep.trial.n_frames > GROUP_FRAMES):
            solve()
        group.append(prep)
    solve()


def _write(tracked: TrackedTrial, output: Path, exports: Sequence[str], overwrite: bool) -> None:
    """The trial's result file, then its exports next to it."""
    from ..io import save_trial

    tracked.save(output, overwrite=overwrite)
    if "bvh" in exports:
        tracked.export_bvh(output.with_suffix(".bvh"), overwrite=overwrite)
    if "trc" in exports:
        save_trial(tracked.fitted_trial(), output.with_suffix(".trc"), overwrite=overwrite)
    if "angles" in exports:
        write_angles_sto(tracked.joint_angles(), output.with_suffix(".sto"), overwrite=overwrite)


# ------------------------------------------------------------------ Dask
def _pack_skeleton(skeleton: Skeleton) -> dict[str, Any]:
    """A skeleton as plain state (its read-only diagnostics mapping does not pickle)."""
    state = {f.name: getattr(skeleton, f.name) for f in dataclasses.fields(skeleton)}
    state["diagnostics"] = dict(skeleton.diagnostics)
    return state


def _track_group(state: dict[str, Any], calibration: Calibration, packed: list[tuple[int, str, Any, str, tuple]],
                 options: FitOptions, exports: list[str], overwrite: bool, batch_size: int) -> list[tuple]:
    """Worker task: track a group of trials in-process and write their files; return a row,
    the error and the packed warnings per trial."""
    from .._runtime.compile_cache import enable_compile_cache
    from ._dask import _unpack
    from ._trial_warnings import pack

    enable_compile_cache()
    skeleton = Skeleton(**state)
    items = [Item(index, name, "", (_unpack(value),), Path(output), reading)
             for index, name, value, output, reading in packed]
    rows: list[tuple] = []

    def on_done(item: Item, outcome: TrialOutcome) -> None:
        rows.append((item.index, dict(outcome.row), outcome.error, pack(outcome.warnings)))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # said again on the client, naming the trial
        _track_local(items, skeleton, calibration, options, exports, overwrite, batch_size, False, on_done)
    return rows


def _track_distributed(items: list[Item], skeleton: Skeleton, calibration: Calibration, options: FitOptions,
                       exports: Sequence[str], overwrite: bool, batch_size: int, scheduler: Any,
                       done: Callable[[Item, TrialOutcome], None]) -> None:
    """Track ``items`` on a Dask cluster: one group of trials per task (at most ``batch_size``,
    one group per worker when there are few)."""
    from ._dask import _pack, dask_client
    from ._trial_warnings import unpack

    with dask_client(scheduler) as (client, n_workers):
        from distributed import as_completed  # importable: dask_client checked

        size = max(1, min(batch_size, math.ceil(len(items) / n_workers)))
        state = _pack_skeleton(skeleton)
        futures = {}
        for i in range(0, len(items), size):
            group = items[i : i + size]
            packed = [(it.index, it.name, _pack(it.inputs[0]), str(it.output), it.load_options) for it in group]
            fut = client.submit(_track_group, state, calibration, packed, options, list(exports), overwrite,
                                batch_size, pure=False)
            futures[fut] = group
        by_index = {it.index: it for it in items}
        for fut in as_completed(list(futures)):
            try:
                rows = fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker fails its trials only
                for it in futures[fut]:
                    done(it, failed(it, RuntimeError(f"Dask task failed: {type(exc).__name__}: {exc}"), 0.0))
                continue
            for index, row, error, packed_warnings in rows:
                it = by_index[index]
                status = row.get("status", "failed")
                done(it, TrialOutcome(it.name, "", status, error=error, output=it.output if status == "ok" else None,
                                      row=row, warnings=unpack(packed_warnings)))
