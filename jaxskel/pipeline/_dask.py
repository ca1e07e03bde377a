"""Scale-out of :func:`jaxskel.fit_batch` on a Dask distributed cluster.

Why Dask (and not Ray): the work is a bag of independent, coarse tasks (a group of
trials takes seconds to minutes) that read and write files; Dask distributed
schedules exactly that with a plain ``Client.submit``, starts a local cluster of
worker *processes* in one line (``LocalCluster(n_workers=2)``), is a pure-Python
``pip install`` (no separate object store or runtime daemon), runs on HPC
schedulers through dask-jobqueue, and is already in the scientific-Python stack
most labs use. Ray would add an actor model and a shared-memory object store that
this workload does not need.

Design: the client groups the trials to fit (those not already finished) into
tasks of up to ``batch_size`` trials (one group per worker when there are few),
ordered by input size so that trials of similar
length share a task (and therefore padded shapes and compiled solvers); each
worker runs the in-process pipeline (:func:`jaxskel.pipeline._batch.run_local`) on its
group with the persistent compilation cache switched on, writes the result files
into the shared output folder, and returns the summary rows. A task that dies
(worker lost, out of memory) marks its trials failed; the others go on, and a
rerun retries them.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from .._errors import InputError
from ._options import FitOptions
from ..io import Trial

__all__ = ["dask_client", "run_distributed"]


def _pack(value: Any) -> Any:
    """Trials travel as plain state (their read-only metadata mapping does not pickle)."""
    if isinstance(value, Trial):
        return ("trial", dict(positions=value.positions, labels=value.labels, rate=value.rate,
                              up_axis=value.up_axis, source=value.source, metadata=dict(value.metadata)))
    return ("path", str(value))


def _unpack(value: Any) -> Any:
    kind, state = value
    return Trial(**state) if kind == "trial" else Path(state)


def _size(item: Any) -> int:
    total = 0
    for v in item.inputs:
        if isinstance(v, (str, os.PathLike)):
            try:
                total += Path(v).stat().st_size
            except OSError:
                pass
        else:
            total += int(v.positions.nbytes)
    return total


def _fit_group(
    packed: list[tuple[int, str, str, list[Any], str | None, tuple[tuple[str, Any], ...]]],
    options: FitOptions,
    bones: Mapping[str, Any],
    signatures: Mapping[int, str],
    batch_size: int,
    memory: int | str | None = "auto",
) -> list[tuple[int, dict[str, Any], str, list[tuple[str, str]]]]:
    """Worker task: fit a group of trials in-process; return (index, row, traceback, warnings)
    per trial (the warnings its fit raised, :func:`jaxskel.pipeline._trial_warnings.pack`ed:
    the client warns them naming the trial, the worker says nothing)."""
    from .._runtime.compile_cache import enable_compile_cache
    from ._local import default_devices, Item, run_local
    from ._trial_warnings import pack

    enable_compile_cache()
    items = [
        Item(index, name, subject, tuple(_unpack(v) for v in inputs), None if out is None else Path(out), reading)
        for index, name, subject, inputs, out, reading in packed
    ]
    rows: list[tuple[int, dict[str, Any], str, list[tuple[str, str]]]] = []

    def on_outcome(item: Any, outcome: Any) -> None:
        rows.append((item.index, dict(outcome.row), outcome.traceback, pack(outcome.warnings)))

    run_local(
        items, options, bones=bones, signatures=signatures, batch_size=batch_size, jobs=2,
        devices=default_devices("auto"), keep_results=False, on_outcome=on_outcome, emit_warnings=False,
        memory=memory,
    )
    return rows


def run_distributed(
    items: Sequence[Any],
    options: FitOptions,
    *,
    scheduler: Any,
    bones: Mapping[str, Any],
    signatures: Mapping[int, str],
    batch_size: int,
    on_outcome: Callable[[Any, Any], None],
    group_size: int | None = None,
    memory: int | str | None = "auto",
) -> None:
    """Fit ``items`` on a Dask cluster (module docstring); report each trial to ``on_outcome``."""
    from ._local import TrialOutcome, failed
    from ._trial_warnings import emit, unpack

    with dask_client(scheduler) as (client, n_workers):
        from distributed import as_completed  # importable: dask_client checked

        # one group per worker, at most batch_size trials each: batching within a worker saves
        # more than finer load balancing would (bench/bench_batch.py: docs/bench/fit_batch_1_8.json)
        size = group_size or max(1, min(batch_size, math.ceil(len(items) / n_workers)))
        ordered = sorted(items, key=_size)
        groups = [ordered[i : i + size] for i in range(0, len(ordered), size)]
        futures = {}
        for group in groups:
            packed = [
                (it.index, it.name, it.subject, [_pack(v) for v in it.inputs], None if it.output is None else str(it.output),
                 it.load_options)
                for it in group
            ]
            sigs = {it.index: signatures.get(it.index, "") for it in group}
            fut = client.submit(_fit_group, packed, options, dict(bones), sigs, batch_size, memory,
                                pure=False)
            futures[fut] = group
        by_index = {it.index: it for it in items}
        for fut in as_completed(list(futures)):
            group = futures[fut]
            try:
                rows = fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker fails its trials only
                for it in group:
                    on_outcome(it, failed(it, RuntimeError(f"Dask task failed: {type(exc).__name__}: {exc}"), 0.0))
                continue
            for index, row, trace, *packed in rows:
                it = by_index[index]
                status = row.get("status", "failed")
                out = it.output if status == "ok" else None
                caught = unpack(packed[0]) if packed else ()
                emit(it.name, caught)  # the worker's warnings, here, naming the trial
                on_outcome(it, TrialOutcome(it.name, it.subject, status, error=row.get("error", ""),
                                            output=out, row=row, traceback=trace, warnings=caught))


@contextlib.contextmanager
def dask_client(scheduler: Any) -> Iterator[tuple[Any, int]]:
    """``(client, number of workers)`` of a Dask ``scheduler``: an address (a client made here,
    closed on exit) or a ``distributed.Client`` (used as it is)."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - depends on the environment
        raise InputError(
            'a scheduler needs Dask distributed: pip install "jaxskel[distributed]" (or "dask[distributed]")'
        ) from None
    own = not isinstance(scheduler, Client)
    try:
        client = Client(scheduler, timeout="30s") if own else scheduler
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"cannot reach the Dask scheduler at {scheduler!r}: {exc}") from None
    try:
        yield client, max(1, len(client.scheduler_info().get("workers", {})))
    finally:
        if own:
            client.close()
