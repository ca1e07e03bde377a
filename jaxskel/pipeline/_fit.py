"""`fit_skeleton`: the whole chain from raw markers to an articulated skeleton.

    Trial --clean--> --[merge labels]--> --segment--> --joint costs / MST / tree joints-->
          --rigid skeleton--> --inverse kinematics--> SkeletonResult

The stages and their order are the :class:`~jaxskel.pipeline.StagePlan`'s, the settings
the :class:`~jaxskel.FitOptions`'; this module builds both from the call and reports
progress.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .._errors import InputError
from .._runtime.map_limit import release_programs_near_map_limit
from .._runtime.precision import float64
from ..io import Trial
from ..result import SkeletonResult
from ._options import FitOptions
from ._plan import StagePlan

__all__ = ["fit_skeleton", "resolve_options"]


def resolve_options(options: FitOptions | None, settings: dict[str, Any]) -> FitOptions:
    """``options`` (default: the defaults) with the flat ``settings`` applied, validated."""
    if options is None:
        options = FitOptions()
    elif not isinstance(options, FitOptions):
        raise InputError(
            f"options must be a jaxskel.FitOptions, got {type(options).__name__}; settings can also be given "
            "by name (fit_skeleton(trial, n_segments=15, ik=False))"
        )
    return options.replace(**settings) if settings else options


def fit_skeleton(
    trial_or_trials: Trial | Sequence[Trial],
    n_segments: int | None = None,
    *,
    options: FitOptions | None = None,
    segment_names: Sequence[str] | None = None,
    progress: bool = False,
    **settings: Any,
) -> SkeletonResult:
    """Fit an articulated skeleton to marker trajectories (Kirk et al. 2005).

    Parameters
    ----------
    trial_or_trials
        One :class:`Trial`, or several trials of one subject with one marker set
        (fitted together: e.g. a range-of-motion trial plus a walk).
    n_segments
        Number of rigid segments, or ``None`` for the automatic count (the setting
        ``n_segments`` of :class:`FitOptions`; given here, it overrides ``options``).
    options
        Every setting of the fit (:class:`jaxskel.FitOptions`); default the defaults.
    segment_names
        Names for the segments (length S); default: readable names from their markers'
        labels (:mod:`jaxskel.segment._names`). Display only.
    progress
        Show a progress bar over the stages.
    **settings
        Settings by their flat names, applied over ``options``: ``ik=False``,
        ``sigma=0.006``, ``merge_labels=True``, ... (:meth:`FitOptions.replace`; an
        unknown name raises :class:`InputError` with the closest known one).
    """
    if n_segments is not None:
        settings = {"n_segments": n_segments, **settings}
    options = resolve_options(options, settings)
    release_programs_near_map_limit(stacklevel=2)  # a long-lived process: XLA crashes past the limit
    bar = None
    plan = StagePlan(options, segment_names=None if segment_names is None else tuple(segment_names))
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(plan.stages), desc="fit_skeleton", unit="stage")

        def on_stage(name: str) -> None:
            bar.set_postfix_str(name)
            bar.update(1)

        def on_more(names: tuple[str, ...]) -> None:  # a grown segment count runs stages again
            bar.total += len(names)
            bar.refresh()

        plan = StagePlan(options, segment_names=plan.segment_names, on_stage=on_stage, on_more=on_more)
    # float64 for this call only; a with block, not a decorator, so that no frame is added
    # between the fit's warnings and the caller they point at
    with float64():
        try:
            result = plan.fit(trial_or_trials, stacklevel=3)  # the caller of fit_skeleton
            if bar is not None and bar.n != bar.total:  # a grown count's refit that stopped early
                bar.total = bar.n
                bar.refresh()
            return result
        finally:
            if bar is not None:
                bar.close()
