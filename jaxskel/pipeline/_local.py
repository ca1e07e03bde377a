"""The in-process batch pipeline of :func:`jaxskel.fit_batch` (its module docstring,
:mod:`jaxskel.pipeline._batch`, describes it): prepare trials in a thread pool, solve the
joint stage of a batch of them in shared vmapped solves, finish each in a thread pool.
The Dask workers (:mod:`jaxskel.pipeline._dask`) run this same pipeline.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from .._errors import InputError, JaxskelError
from .._runtime.map_limit import near_map_limit, release_programs_near_map_limit
from .._runtime.precision import float64_scope
from ..joints import Topology
from ._batch_io import (
    BoneSpec,
    completion_record,
    failed_row,
    summary_row,
)
from ._batch_memory import fit_bytes, memory_budget
from ._options import FitOptions
from ._plan import PreparedFit, StagePlan, moving_frames
from ._trial_warnings import Caught, TrialWarnings, emit

__all__ = ["DEVICE_LOCK", "Item", "TrialOutcome", "default_devices", "failed", "run_local"]

#: Held around every stage that runs JAX code. Two XLA:CPU executions at once (two threads,
#: or two forced host devices) can hang for good: batched LAPACK kernels (the rigid fit's
#: SVD and Cholesky still are) split their batch over XLA's intra-op pool with
#: ``ParallelBatchMap`` and block a pool thread until the pieces finish; with two threads
#: and two such calls, both wait for work queued behind the other (a batch that hung so,
#: and the fix: docs/bench/batch_hang_stress.md). So the pipeline overlaps only numpy/IO
#: work with the device, and more cores are used through processes (Dask workers).
DEVICE_LOCK = threading.RLock()


# ----------------------------------------------------------------------- items
@dataclasses.dataclass(frozen=True)
class Item:
    index: int
    name: str
    subject: str
    inputs: tuple[Any, ...]  # paths and/or Trials, fitted together
    output: Path | None
    #: jaxskel.load's units= and up_axis= for the paths, as (name, value) pairs
    load_options: tuple[tuple[str, Any], ...] = ()

    def inputs_text(self) -> str:
        return "; ".join(str(v) if isinstance(v, (str, os.PathLike)) else (v.source or "<trial>") for v in self.inputs)

    def trials(self) -> list[Any]:
        """The inputs as Trials: paths read with :attr:`load_options` (no unit for HDF5 trials, always metres)."""
        from ..io import load

        out = []
        for v in self.inputs:
            if isinstance(v, (str, os.PathLike)):
                kwargs = dict(self.load_options)
                if Path(v).suffix.lower() in (".h5", ".hdf5"):
                    kwargs.pop("units", None)
                v = load(v, **kwargs)
            out.append(v)
        return out


@dataclasses.dataclass(frozen=True)
class TrialOutcome:
    """What happened to one trial of a batch.

    ``status`` is ``"ok"`` (fitted now), ``"skipped"`` (a complete result with the
    same inputs and settings was already there) or ``"failed"`` (``error`` says
    why; ``traceback`` is set for unexpected, non-jaxskel errors). ``result`` is
    the :class:`jaxskel.SkeletonResult` when kept in memory; ``output`` the
    result file; ``row`` the summary-table row; ``warnings`` the warnings its fit
    raised, ``(category, text)`` each once (:func:`jaxskel.fit_batch` also warns
    them again, naming the trial: :mod:`jaxskel.pipeline._trial_warnings`).
    """

    name: str
    subject: str
    status: str
    error: str = ""
    output: Path | None = None
    result: Any = None
    row: dict[str, Any] = dataclasses.field(default_factory=dict)
    traceback: str = ""
    warnings: tuple[Caught, ...] = ()

    @property
    def ok(self) -> bool:
        return self.status in ("ok", "skipped")

    def load(self) -> Any:
        """The result file read back (:func:`jaxskel.load_result`)."""
        from ..result import load_result

        if self.output is None:
            raise InputError(f"{self.name}: no result file (fit_batch ran without an output folder)")
        return load_result(self.output)


def _error_text(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def failed(item: Item, exc: BaseException, seconds: float) -> TrialOutcome:
    trace = "" if isinstance(exc, JaxskelError) else "".join(traceback.format_exception(exc))
    row = failed_row(name=item.name, subject=item.subject, inputs=item.inputs_text(),
                     output="", error=_error_text(exc), seconds=seconds)
    return TrialOutcome(item.name, item.subject, "failed", error=row["error"], row=row, traceback=trace)


# ----------------------------------------------------------------- the pipeline
@dataclasses.dataclass
class _Work:
    item: Item
    t0: float
    prep: PreparedFit | None = None
    pairs: Any = None  # the joints stage's AllPairsProblem, freed once solved
    tree: Any = None  # the joints stage's TreeProblem, freed once solved
    topology: Topology | None = None


@float64_scope
def _prepare(item: Item, options: FitOptions) -> _Work:
    from ..joints import all_pairs_problem

    work = _Work(item, time.perf_counter())
    t0 = time.perf_counter()
    trials = item.trials()
    load_s = time.perf_counter() - t0
    plan = StagePlan(options, device_lock=DEVICE_LOCK)
    work.prep = plan.prepare(trials)
    work.prep.timings["load"] = load_s
    j = options.joints
    with plan.stage(work.prep, "joint costs"):
        work.pairs = all_pairs_problem(
            moving_frames(work.prep.trial, work.prep.segmentation), work.prep.segmentation, alpha=j.alpha,
            max_frames=j.topology_frames, method=j.method,
        )
    return work


def _shared(works: list[_Work], solve: Callable[[list[Any]], list[Any]], attr: str, fail: Callable) -> list[Any]:
    """Run one shared solve; if it raises, retry trial by trial so only the culprit fails."""
    problems = [getattr(w, attr) for w in works]
    try:
        return solve(problems)
    except Exception:  # noqa: BLE001 - isolate the failing trial
        out = []
        for w, p in zip(works, problems):
            try:
                out.append(solve([p])[0])
            except Exception as exc:  # noqa: BLE001
                fail(w, exc)
                out.append(None)
        return out


def _solve_batch(works: list[_Work], options: FitOptions, devices: Any, fail: Callable,
                 within: Callable[[Item], Any] = lambda item: contextlib.nullcontext()) -> list[_Work]:
    """All-pairs costs, then tree joints, of several prepared trials together; each trial's
    own steps run ``with within(item)`` (its warnings are caught for it)."""
    from ..joints import (
        pair_costs_from,
        solve_pairs,
        solve_trees,
        topology_from,
        tree_problem,
    )

    plan, j = StagePlan(options), options.joints
    t0 = time.perf_counter()
    with DEVICE_LOCK:
        sols = _shared(works, lambda ps: solve_pairs(ps, devices=devices), "pairs", fail)
    share = (time.perf_counter() - t0) / max(len(works), 1)
    alive = []
    for w, sol in zip(works, sols):
        if sol is None:
            continue
        try:
            with within(w.item), plan.stage(w.prep, "joint costs"):
                pair_costs = pair_costs_from(w.pairs, sol)
            # the pose check inside runs JAX code (segment poses): under the lock, like every
            # other JAX stage, or it overlaps a finishing trial's programs and both hang
            with within(w.item), plan.stage(w.prep, "tree joints"), DEVICE_LOCK:
                w.tree = tree_problem(
                    moving_frames(w.prep.trial, w.prep.segmentation), w.prep.segmentation, pair_costs, root=j.root,
                    alpha=j.alpha, alpha_tree=j.alpha_tree, method=j.method, pose_check=j.pose_check,
                )
            w.prep.timings["joint costs"] += share
            w.pairs = None  # free the padded arrays
            alive.append(w)
        except Exception as exc:  # noqa: BLE001
            fail(w, exc)
    t0 = time.perf_counter()
    with DEVICE_LOCK:
        sols = _shared(alive, lambda ps: solve_trees(ps, devices=devices), "tree", fail)
    share = (time.perf_counter() - t0) / max(len(alive), 1)
    done = []
    for w, sol in zip(alive, sols):
        if sol is None:
            continue
        try:
            with within(w.item):
                w.topology = topology_from(w.tree, sol)
            w.prep.timings["tree joints"] += share
            w.tree = None
            done.append(w)
        except Exception as exc:  # noqa: BLE001
            fail(w, exc)
    return done


@float64_scope
def _finish(work: _Work, options: FitOptions, bones: Mapping[str, BoneSpec], sig: str | None,
            keep: bool) -> TrialOutcome:
    item, prep = work.item, work.prep
    # the rest of the plan, as fit_skeleton runs it (a segment the rigid skeleton cannot hold
    # grows the automatic count, and the skeleton checks the label merges; such refits run
    # unbatched, this one trial's joint and skeleton stages)
    with DEVICE_LOCK:
        result = StagePlan(options).complete(prep, work.topology)
    seconds = sum(result.timings.values())  # this trial's share of the work, not its latency
    row = summary_row(
        result, name=item.name, subject=item.subject, inputs=item.inputs_text(),
        output="" if item.output is None else str(item.output), seconds=seconds, bones=bones,
    )
    if item.output is not None:
        item.output.parent.mkdir(parents=True, exist_ok=True)
        result.save(item.output, overwrite=True, extra_groups={"batch": completion_record(sig or "", row)})
    return TrialOutcome(item.name, item.subject, "ok", output=item.output, result=result if keep else None, row=row)


@float64_scope
def run_local(
    items: Sequence[Item],
    options: FitOptions,
    *,
    bones: Mapping[str, BoneSpec],
    signatures: Mapping[int, str],
    batch_size: int,
    jobs: int,
    devices: Any,
    keep_results: bool,
    on_outcome: Callable[[Item, TrialOutcome], None],
    emit_warnings: bool = True,
    memory: int | str | None = "auto",
) -> None:
    """The in-process pipeline (module docstring); reports every trial to ``on_outcome``.

    The trials solved together are at most ``batch_size`` and, but for a trial alone,
    within ``memory`` (:func:`jaxskel.pipeline._batch_memory.memory_budget`, resolved now)
    by their estimated peak (:func:`jaxskel.pipeline._batch_memory.fit_bytes`), counted
    with the trials still being finished (rigid fit, IK, writing) from earlier batches.

    Each trial's warnings are caught for it (:mod:`jaxskel.pipeline._trial_warnings`) and
    travel in its outcome (``TrialOutcome.warnings``); with ``emit_warnings`` they are
    also warned again, naming the trial, from this (the calling) thread.
    """
    budget = memory_budget(memory)
    prep_pool = ThreadPoolExecutor(jobs, thread_name_prefix="jaxskel-prepare")
    finish_pool = ThreadPoolExecutor(jobs, thread_name_prefix="jaxskel-finish")
    waiting = collections.deque(items)
    preparing: collections.deque[tuple[Item, Future]] = collections.deque()
    finishing: list[Future] = []
    finishing_bytes: dict[Future, int] = {}  # estimated peak of each trial being finished
    caught = TrialWarnings(records_under=DEVICE_LOCK)
    unsaid: collections.deque[tuple[str, tuple[Caught, ...]]] = collections.deque()

    def report(item: Item, outcome: TrialOutcome) -> None:
        outcome = dataclasses.replace(outcome, warnings=caught.take(item.index))
        if emit_warnings and outcome.warnings:
            unsaid.append((item.name, outcome.warnings))
        on_outcome(item, outcome)

    def say_warnings() -> None:
        # Under the lock no thread records warnings (StagePlan.grow_count does so under it),
        # so these reach the caller's display, not another trial's record.
        with DEVICE_LOCK:
            caught.heal()
            while unsaid:
                emit(*unsaid.popleft(), stacklevel=3)

    def fail(work: _Work, exc: BaseException) -> None:
        report(work.item, failed(work.item, exc, time.perf_counter() - work.t0))

    def prepare(item: Item) -> _Work:
        with caught.trial(item.index):
            return _prepare(item, options)

    def top_up() -> None:
        while waiting and len(preparing) < batch_size + jobs:
            item = waiting.popleft()
            preparing.append((item, prep_pool.submit(prepare, item)))

    def finish(work: _Work) -> None:
        with caught.trial(work.item.index):
            try:
                outcome = _finish(work, options, bones, signatures.get(work.item.index), keep_results)
            except Exception as exc:  # noqa: BLE001
                outcome = failed(work.item, exc, time.perf_counter() - work.t0)
        report(work.item, outcome)

    with caught.installed():
        try:
            top_up()
            while preparing:
                # A full batch (or what is left): while the main thread waits, the lock is free
                # for the finishing stage of the previous batch and the preparation of this one.
                # trials still being finished count against the memory bound too
                finishing_bytes = {f: b for f, b in finishing_bytes.items() if not f.done()}
                ready, held = [], sum(finishing_bytes.values())
                while preparing and len(ready) < batch_size:
                    nxt = preparing[0][1]
                    need = 0 if nxt.exception() is not None else _work_bytes(nxt.result())  # waits for it
                    if ready and budget is not None and held + need > budget:
                        break  # the next batch takes it: this one would not fit in memory
                    ready.append(preparing.popleft())
                    held += need
                    top_up()
                works = []
                for item, fut in ready:
                    exc = fut.exception()
                    if exc is not None:
                        report(item, failed(item, exc, 0.0))
                    else:
                        works.append(fut.result())
                if works:
                    if near_map_limit():
                        # XLA crashes past the kernel's mapping limit; JAX's programs may be
                        # dropped only while no other thread runs them (jaxskel._runtime.map_limit)
                        for fut in finishing:
                            fut.exception()
                        for _, fut in preparing:
                            fut.exception()
                        release_programs_near_map_limit(stacklevel=1)
                    for work in _solve_batch(works, options, devices, fail, lambda item: caught.trial(item.index)):
                        finishing.append(finish_pool.submit(finish, work))
                        finishing_bytes[finishing[-1]] = _work_bytes(work)
                say_warnings()
                # keep memory bounded: at most 2 jobs' worth of trials waiting to be finished
                while sum(not f.done() for f in finishing) > 2 * jobs:
                    next(f for f in finishing if not f.done()).exception()
                top_up()
            for f in finishing:
                f.result()
        finally:
            prep_pool.shutdown(wait=True, cancel_futures=True)
            finish_pool.shutdown(wait=True, cancel_futures=True)
            say_warnings()


def _work_bytes(work: _Work) -> int:
    """Estimated peak bytes of fitting a prepared trial (:func:`jaxskel.pipeline._batch_memory.fit_bytes`)."""
    return fit_bytes(work.prep.trial.n_frames, work.prep.trial.n_markers)


def default_devices(devices: Any) -> Any:
    if devices is None or devices == "auto":
        import jax

        local = jax.local_devices()
        return local if len(local) > 1 else None
    if devices == "default":
        return None
    return list(devices)


