"""The warnings a fit raises about its own result, and the one-tree requirement.

Each names the segments and joints concerned and what would fix them. They are raised
from inside :meth:`jaxskel.pipeline.StagePlan.skeleton`; :data:`STACKLEVEL` points them at
the caller of :func:`jaxskel.fit_skeleton` on the direct path (warnings of fits that the
automatic count discards are recorded and only the kept fit's are re-emitted, at the
caller: :mod:`jaxskel.pipeline._split_refit`).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from .._errors import AmbiguousTreeWarning, DegenerateMotionError, DegenerateMotionWarning, NonRigidMarkerWarning
from ..joints import Topology
from ..result import near_tie_text, nonrigid_group_hint, nonrigid_group_texts, undetermined_lines, untested_text
from ..segment import Segmentation

__all__ = [
    "STACKLEVEL", "require_one_tree", "warn_near_ties", "warn_nonrigid_groups", "warn_undetermined",
    "warn_unexercised", "warn_untested",
]

#: warn_* <- StagePlan.skeleton <- refit <- _confirm_merges <- complete <- fit <- fit_skeleton
#: <- its caller: the frames from a warning to the user's call on the one path whose warnings
#: are not recorded and re-emitted (the refit after the label merges were corrected)
STACKLEVEL = 8


def warn_unexercised(exercise: np.ndarray, joint_names: Sequence[str]) -> None:
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
            stacklevel=STACKLEVEL,
        )


def warn_undetermined(skeleton: Any, names: Sequence[str]) -> None:
    """A :class:`DegenerateMotionWarning` naming the joints the recording fixes only loosely
    (:func:`jaxskel.joints.undetermined_joints`) and the motion each lacks."""
    from ..joints import undetermined_joints

    loose = undetermined_joints(skeleton)
    if loose:
        text = undetermined_lines([u.joint for u in loose], names, skeleton)
        warnings.warn(
            f"{len(loose)} joint(s) " + "\n".join(text),
            DegenerateMotionWarning,
            stacklevel=STACKLEVEL,
        )


def warn_nonrigid_groups(seg: Segmentation, names: Sequence[str]) -> None:
    """A :class:`NonRigidMarkerWarning` naming the segments whose groups are not rigid."""
    groups = nonrigid_group_texts(seg, names)
    if groups:
        warnings.warn(
            f"{len(groups)} segment(s) not rigid:\n" + "\n".join(groups) + "\n" + nonrigid_group_hint(seg),
            NonRigidMarkerWarning,
            stacklevel=STACKLEVEL,
        )


def require_one_tree(topology: Topology, segmentation: Segmentation, names: Sequence[str]) -> None:
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


def warn_untested(untested: list, names: Sequence[str], sizes: np.ndarray) -> None:
    """A :class:`DegenerateMotionWarning` naming attachments the joint costs could not test."""
    if untested:
        warnings.warn(
            "the tree may attach sparsely marked segments to the wrong neighbour:\n"
            + "\n".join(untested_text(u, names, sizes) for u in untested),
            DegenerateMotionWarning,
            stacklevel=STACKLEVEL,
        )


def warn_near_ties(ties: list, names: Sequence[str]) -> None:
    """An :class:`AmbiguousTreeWarning` naming the tree joints the costs cannot tell from a rival."""
    if ties:
        warnings.warn(
            f"{len(ties)} joint(s) of the tree are not settled by the data:\n"
            + "\n".join(near_tie_text(t, names) for t in ties)
            + "\nCheck them (summary, --plot), or fit with a trial that exercises those joints",
            AmbiguousTreeWarning,
            stacklevel=STACKLEVEL,
        )
