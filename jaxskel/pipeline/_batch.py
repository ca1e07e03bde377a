"""`fit_batch`: many trials, fitted together, resumably, one result file each.

Pipeline (one process)::

    load, clean, merge labels, segment  ──(thread pool, ``jobs`` threads)──┐
                                                                          ▼
    all-pairs joint costs of every ready trial  ── one chunked vmapped solve ──┐
    tree joints of the same trials              ── one chunked vmapped solve ──┤  (main thread,
                                                                          ▼    devices round-robin)
    rigid skeleton, IK, write result + completion record ──(thread pool)──┘

* **Batched core.** The candidate segment pairs of all trials whose padded shapes
  agree (frame bucket, marker bucket) are concatenated and solved in the same
  fixed-size chunks (``PAIR_CHUNK`` pairs, ``PAIR_CHUNK_CPU`` on a CPU;
  :func:`jaxskel.joints._topology.solve_chunked`); the tree joints
  of those trials are pooled, sorted by their first-pass step count and solved in
  shared chunks as well. A pair's solution does not depend on its chunk mates (the
  vmapped while loop freezes finished pairs), so every trial gets exactly what
  :func:`jaxskel.fit_skeleton` gives it alone (tested).
* **Overlap.** Host-side stages of later trials (reading, cleaning, spectral
  clustering) and the rigid fit, IK and writing of earlier ones run in thread pools
  while the main thread runs the batched solves. Stages that run JAX code take
  :data:`DEVICE_LOCK` (XLA:CPU hangs on concurrent executions, see below), so on CPU
  only numpy and file work overlaps with the solves; the rigid fit and IK of the
  previous batch run while the main thread waits for the next batch to be prepared.
* **Devices.** Chunks go round-robin to ``devices`` (default: every local device
  of JAX's default backend), dispatched asynchronously, so two GPUs (or CPU
  "devices" forced with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``)
  work at once.
* **Failures.** A trial that raises becomes a row with ``status="failed"`` and the
  error; the others go on. An error inside a shared solve is retried trial by
  trial so that only the culprit fails.
* **Resumable.** Each result file is written atomically and carries a completion
  record (``/batch``: inputs' path/size/mtime, settings, summary row). A rerun
  skips trials whose record matches; anything else (no file, a truncated or
  foreign file, changed input or settings) is fitted again. Failed trials leave no
  file, so a rerun retries them.
* **Scale-out.** ``scheduler=`` sends groups of trials to a Dask cluster
  (:mod:`jaxskel.pipeline._dask`); each worker runs this same pipeline.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from .._errors import InputError, JaxskelError
from .._runtime.precision import float64_scope
from ..io import Trial, check_load_arguments
from ._batch_io import (
    BoneSpec,
    _normalise_specs,
    finished_row,
    signature,
    write_summary,
)
from ._batch_memory import parse_memory
from ._fit import resolve_options
from ._options import FitOptions
from ._local import Item, TrialOutcome, default_devices, failed, run_local

__all__ = ["fit_batch", "BatchResult", "TrialOutcome", "discover_trials"]

#: Recording suffixes :func:`discover_trials` picks up.
SUFFIXES = (".c3d", ".trc", ".csv", ".h5", ".hdf5")


def _is_result_file(path: Path) -> bool:
    if path.suffix.lower() not in (".h5", ".hdf5"):
        return False
    try:
        import h5py

        with h5py.File(path, "r") as f:
            return "schema_version" in f.attrs
    except OSError:
        return False


def discover_trials(directory: str | os.PathLike[str], *, exclude: str | os.PathLike[str] | None = None) -> list[Path]:
    """Recordings under ``directory`` (recursive; .c3d .trc .csv and trial .h5), sorted.

    Result files (HDF5 with a ``schema_version``) and anything under ``exclude``
    (the output folder) are left out.
    """
    root = Path(directory)
    if not root.is_dir():
        raise InputError(f"{root}: not a directory; fit-batch takes a folder of recordings")
    skip = Path(exclude).resolve() if exclude is not None else None
    found = []
    for path in sorted(root.rglob("*")):
        if not path.is_file() or path.suffix.lower() not in SUFFIXES or path.name.startswith("."):
            continue
        if skip is not None and skip in path.resolve().parents:
            continue
        if _is_result_file(path):
            continue
        found.append(path)
    return found


def _trial_name(value: Any, index: int) -> str:
    if isinstance(value, (str, os.PathLike)):
        return Path(value).stem
    source = getattr(value, "source", "") or ""
    stem = Path(source).stem if source and ("/" in source or "." in source) and ":" not in source else ""
    return stem or f"trial{index:03d}"


def _resolve_items(
    trials: Any,
    outdir: Path | None,
    names: Sequence[str] | None,
    subjects: Sequence[str] | None,
) -> list[Item]:
    if isinstance(trials, (str, os.PathLike)) and Path(trials).is_dir():
        root = Path(trials)
        paths = discover_trials(root, exclude=outdir)
        if not paths:
            raise InputError(f"{root}: no recordings (.c3d, .trc, .csv, .h5) found")
        rel = [p.relative_to(root) for p in paths]
        auto_names = [r.with_suffix("").as_posix() for r in rel]
        auto_subjects = [r.parts[0] if len(r.parts) > 1 else "" for r in rel]
        entries: list[tuple[Any, ...]] = [(p,) for p in paths]
    else:
        if isinstance(trials, (str, os.PathLike, Trial)):
            trials = [trials]
        if not isinstance(trials, Sequence) or not trials:
            raise InputError("fit_batch takes a folder, or a non-empty list of trials / paths / lists of them")
        entries = []
        for i, item in enumerate(trials):
            group = tuple(item) if isinstance(item, Sequence) and not isinstance(item, (str, Trial)) else (item,)
            if not group or not all(isinstance(v, (str, os.PathLike, Trial)) for v in group):
                raise InputError(
                    f"fit_batch item {i} must be a Trial, a path, or a list of those (one subject), got {item!r:.80}"
                )
            entries.append(group)
        auto_names = [_trial_name(group[0], i) for i, group in enumerate(entries)]
        auto_subjects = [""] * len(entries)
    if names is not None:
        names = [str(n) for n in names]
        if len(names) != len(entries):
            raise InputError(f"{len(names)} names for {len(entries)} trials")
        if len(set(names)) != len(names):
            raise InputError("trial names must be unique (they name the result files)")
    else:
        names, seen = [], collections.Counter()
        for n in auto_names:
            seen[n] += 1
            names.append(n if seen[n] == 1 else f"{n}_{seen[n]}")
    if subjects is not None and len(subjects) != len(entries):
        raise InputError(f"{len(subjects)} subjects for {len(entries)} trials")
    subj = [str(s) for s in subjects] if subjects is not None else auto_subjects
    return [
        Item(i, n, s, e, None if outdir is None else outdir / f"{n}.h5")
        for i, (n, s, e) in enumerate(zip(names, subj, entries))
    ]


# --------------------------------------------------------------------- outcomes
class BatchResult(Sequence[TrialOutcome]):
    """Outcomes of :func:`fit_batch`, in input order (a sequence of :class:`TrialOutcome`)."""

    def __init__(self, outcomes: Sequence[TrialOutcome], summary: Path | None, seconds: float):
        self.outcomes = list(outcomes)
        self.summary = summary
        self.seconds = seconds

    def __len__(self) -> int:
        return len(self.outcomes)

    def __getitem__(self, i: Any) -> Any:
        return self.outcomes[i]

    def __iter__(self) -> Iterator[TrialOutcome]:
        return iter(self.outcomes)

    @property
    def results(self) -> list[Any]:
        """The in-memory results (``None`` for failed, skipped or not kept)."""
        return [o.result for o in self.outcomes]

    @property
    def failed(self) -> list[TrialOutcome]:
        return [o for o in self.outcomes if o.status == "failed"]

    def counts(self) -> dict[str, int]:
        return dict(collections.Counter(o.status for o in self.outcomes))

    def table(self) -> list[dict[str, Any]]:
        """The summary rows (as in the CSV)."""
        return [dict(o.row) for o in self.outcomes]

    def __repr__(self) -> str:
        c = self.counts()
        return (
            f"BatchResult({len(self)} trials: {c.get('ok', 0)} ok, {c.get('skipped', 0)} skipped, "
            f"{c.get('failed', 0)} failed, {self.seconds:.1f} s)"
        )


@float64_scope
def fit_batch(
    trials: Any,
    outdir: str | os.PathLike[str] | None = None,
    *,
    options: FitOptions | None = None,
    names: Sequence[str] | None = None,
    subjects: Sequence[str] | None = None,
    bones: Mapping[str, Any] | None = None,
    batch_size: int = 8,
    memory: int | str | None = "auto",
    jobs: int = 2,
    devices: Any = "auto",
    scheduler: Any = None,
    overwrite: bool = False,
    keep_results: bool | None = None,
    summary: str | None = "summary.csv",
    progress: bool = False,
    units: str | None = None,
    up_axis: str | None = None,
    **settings: Any,
) -> BatchResult:
    """Fit a skeleton to each of many trials: batched, overlapped, resumable.

    Each item is fitted as :func:`jaxskel.fit_skeleton` would fit it alone (same
    results), but the all-pairs joint costs and the tree joints of trials that are
    ready together go through shared vmapped solves, and reading, cleaning,
    segmentation, the rigid fit, IK and writing overlap with them (module
    docstring of :mod:`jaxskel.pipeline._batch`).

    Parameters
    ----------
    trials
        A folder (every recording under it, recursively; see :func:`discover_trials`),
        or a list whose items are a :class:`jaxskel.Trial`, a path, or a list of
        those (several trials of one subject, fitted together).
    outdir
        Folder for one result file per trial (``<name>.h5``, sub-folders kept) and
        the summary table. Without it, nothing is written and results are returned.
    options, **settings
        Every setting of the fit, the same for every trial: a :class:`jaxskel.FitOptions`
        and flat overrides by name, as in :func:`jaxskel.fit_skeleton`.
    names, subjects
        Per-item names (result file names) and subject labels (summary column,
        plot groups). Defaults: the path relative to the folder without suffix, and
        its first folder (``DIR/subject/trial.c3d``); file stems for lists.
    bones
        Bone lengths to tabulate, ``{name: (A, S, B)}`` by marker labels or a list
        of such triples to average (see :func:`jaxskel.pipeline.plot_bone_lengths`); each
        becomes a ``bone:<name>`` column.
    batch_size
        Most trials solved together.
    memory
        Most memory the trials solved together may take, by their estimated peak
        (:func:`jaxskel.pipeline._batch_memory.fit_bytes`: 14 times a trial's positions
        array), with the trials of earlier batches still being finished: a batch closes
        early where the next trial would pass it, and a trial over it alone is solved
        alone. ``"auto"`` (default): half the memory the process can still allocate when
        the trials start (on each Dask worker, the worker's); a number of bytes or text
        such as ``"6GB"``; ``None``: ``batch_size`` alone.
    jobs
        Threads for the host-side stages (each of the two pools).
    devices
        JAX devices to spread chunks over: ``"auto"`` (all local devices of the
        default backend), ``"default"`` (the default device only) or a list.
    scheduler
        A Dask scheduler address (``"tcp://host:8786"``) or a ``distributed.Client``:
        groups of trials are fitted on the cluster's workers (needs ``outdir`` on
        a file system the workers share; ``pip install "jaxskel[distributed]"``).
    overwrite
        Fit every trial again even if a complete result is there.
    keep_results
        Keep every :class:`~jaxskel.SkeletonResult` in memory (default: only when
        there is no ``outdir``).
    summary
        File name of the summary CSV in ``outdir`` (``None``: none).
    progress
        Show a progress bar over trials.
    units, up_axis
        How paths are read (:func:`jaxskel.load`'s arguments; ``units`` is not applied
        to HDF5 trials, which are always metres). Part of the completion record, so a
        rerun with other values fits again.

    Returns
    -------
    :class:`BatchResult`: one :class:`TrialOutcome` per item, in input order. A
    failed trial does not raise; it is reported (``status == "failed"``).
    """
    t_start = time.perf_counter()
    out = None if outdir is None else Path(outdir)
    if scheduler is not None and out is None:
        raise InputError("fit_batch with a scheduler needs outdir: the workers write the result files there")
    options = resolve_options(options, settings)
    check_load_arguments(units, up_axis)
    if int(batch_size) < 1 or int(jobs) < 1:
        raise InputError(f"batch_size and jobs must be >= 1, got {batch_size} and {jobs}")
    memory = parse_memory(memory)
    if out is not None:
        if out.exists() and not out.is_dir():
            raise InputError(f"{out} exists and is not a folder")
        out.mkdir(parents=True, exist_ok=True)
    reading = tuple((k, v) for k, v in (("units", units), ("up_axis", up_axis)) if v is not None)
    items = [dataclasses.replace(item, load_options=reading) for item in _resolve_items(trials, out, names, subjects)]
    specs = _normalise_specs(bones)
    keep = (out is None) if keep_results is None else bool(keep_results)

    outcomes: dict[int, TrialOutcome] = {}
    lock = threading.Lock()
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(items), desc="fit_batch", unit="trial")
    summary_path = None if (out is None or not summary) else out / summary

    def rows_so_far() -> list[dict[str, Any]]:
        return [outcomes[i].row for i in sorted(outcomes)]

    def on_outcome(item: Item, outcome: TrialOutcome) -> None:
        with lock:
            outcomes[item.index] = outcome
            if bar is not None:
                c = collections.Counter(o.status for o in outcomes.values())
                bar.set_postfix(ok=c.get("ok", 0), skipped=c.get("skipped", 0), failed=c.get("failed", 0))
                bar.update(1)
            if summary_path is not None:
                write_summary(summary_path, rows_so_far())

    # Resume: trials with a complete result of the same inputs and settings are skipped.
    signatures: dict[int, str] = {}
    todo = []
    for item in items:
        if item.output is None:
            todo.append(item)
            continue
        try:
            signatures[item.index] = signature(item.inputs, {**options.as_flat(), **dict(reading)})
        except OSError as exc:
            on_outcome(item, failed(item, InputError(f"{item.inputs_text()}: cannot read ({exc})"), 0.0))
            continue
        row = None if overwrite else finished_row(item.output, signatures[item.index])
        if row is not None:
            row = dict(row, status="skipped", error="")
            if specs:
                _refresh_bones(row, item.output, specs)
            on_outcome(item, TrialOutcome(item.name, item.subject, "skipped", output=item.output, row=row))
        else:
            todo.append(item)

    try:
        if todo and scheduler is not None:
            from ._dask import run_distributed

            run_distributed(
                todo, options, scheduler=scheduler, bones=specs, signatures=signatures,
                batch_size=int(batch_size), memory=memory, on_outcome=on_outcome,
            )
        elif todo:
            run_local(
                todo, options, bones=specs, signatures=signatures, batch_size=int(batch_size), jobs=int(jobs),
                devices=default_devices(devices), keep_results=keep, on_outcome=on_outcome, memory=memory,
            )
    finally:
        if bar is not None:
            bar.close()
        if summary_path is not None and outcomes:
            with lock:
                write_summary(summary_path, rows_so_far())
    return BatchResult([outcomes[i.index] for i in items], summary_path, time.perf_counter() - t_start)


def _refresh_bones(row: dict[str, Any], path: Path, specs: Mapping[str, BoneSpec]) -> None:
    """Bone columns of a skipped trial, from its result file (the specs may be new)."""
    from ..result import load_result
    from ._batch_io import bone_length

    try:
        result = load_result(path)
    except JaxskelError:
        return
    for bone, spec in specs.items():
        value = bone_length(result, spec)
        row[f"bone:{bone}"] = round(value, 6) if math.isfinite(value) else math.nan
