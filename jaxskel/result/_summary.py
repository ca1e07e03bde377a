"""The summary's words for what a fit does not know, and for how its tree was chosen.

Undetermined joints. A joint's resolution (:mod:`jaxskel.joints._determination`) is how far its
centre can move before the fixed-centre fit's misfit doubles. Past
:data:`jaxskel.joints._determination.UNDETERMINED_RESOLUTION` (10 cm) it is no size of anything
(a flat direction reads metres), so the text never prints it, nor a bound derived from
it, as a length: the joint reads ``undetermined`` and a bone ending at it
``undetermined (joint X)``. The numbers stay in the result file
(``/joints/resolution``, ``/skeleton/bone_uncertainty``) and in
:meth:`jaxskel.SkeletonResult.joint_resolutions`.

What would fix such a joint comes from its fixed-centre fit: the sweep of the other
segment's markers about it (``skeleton.diagnostics["anchored"]["exercise"]``) and the
way its least determined direction runs (:func:`jaxskel.joints._determination.radial_share`):

* a sweep below :data:`jaxskel.joints._anchored_centres.MIN_EXERCISE_DEG`: the recording barely
  turns the joint; any rotation would help;
* one loose direction, mostly (``cos^2 >= 2/3``, RMS over the markers) along the lines to
  the markers: the arc is too short to fix their distance from the centre; a larger
  range of rotation would;
* one loose direction mostly across them (``cos^2 <= 1/3``): the recording turns the
  joint about that direction, and the centre slides along this axis; rotation about
  other axes would fix it;
* two loose directions, or one in between: both are named.

The tree. The summary says how the tree was chosen (the minimum spanning tree of the joint
costs between segments of two or more markers, the one-marker segments hung from their
most rigid segment, :mod:`jaxskel.joints._attachments`; the pose check's exchanges; the root) and
how close the runner-up tree came: of the trees differing in one joint chosen by cost,
the one whose swapped pair costs the least more than the joint it replaces
(:func:`jaxskel.joints._near_ties.runner_up` on the core's costs: the same rivals as the near
ties, attachments left out).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from ..joints import MIN_EXERCISE_DEG, UNDETERMINED_RESOLUTION
from ..segment import Segmentation

__all__ = [
    "near_tie_text", "nonrigid_group_hint", "nonrigid_group_texts", "nonrigid_text", "pose_exchange_text",
    "untested_text",
    "bone_bound", "is_loose", "millimetres", "missing_motion", "resolution_cell", "tree_lines", "undetermined_lines",
]

#: A direction whose squared cosine with the markers' directions reaches this is along
#: them; one at or below 1 minus it runs across them; in between, neither.
_RADIAL = 2.0 / 3.0

_WORD = "undetermined"


def millimetres(length: float) -> str:
    """A length in metres as millimetres, 7 wide; ``n/a`` unknown."""
    if not np.isfinite(length):
        return "    n/a"
    return f"{1000 * length:7.1f}"


def is_loose(resolution: float) -> bool:
    """Whether a joint's resolution (metres) makes it undetermined."""
    return bool(resolution > UNDETERMINED_RESOLUTION)


def resolution_cell(resolution: float) -> str:
    """The joints table's resolution: millimetres, or ``undetermined`` past the limit."""
    return _WORD if is_loose(resolution) else millimetres(resolution)


def bone_bound(ends: Sequence[int], resolution: np.ndarray, bound: float, joint_name: Callable[[int], str]) -> str:
    """The bone table's bound of a bone between joints ``ends``: ``undetermined (joint X)``
    where an end is undetermined, ``>=`` the millimetres where an end is unknown (its
    share missing), else the millimetres."""
    loose = [j for j in ends if is_loose(resolution[j])]
    if loose:
        return f"{_WORD} (joint{'s' if len(loose) > 1 else ''} {', '.join(joint_name(j) for j in loose)})"
    partial = np.isfinite(bound) and not np.isfinite(resolution[list(ends)]).all()
    return f"{'>=' if partial else '  '}{millimetres(bound)}"


def missing_motion(parent: str, child: str, sweep: float, radial: float, loose: int, markers_of: str) -> str:
    """The motion that would fix a joint between ``parent`` and ``child`` (module docstring).

    ``sweep`` (degrees) is its exercise, ``radial`` the
    :func:`jaxskel.joints._determination.radial_share` of its least
    determined direction, ``loose`` how many directions are undetermined, and
    ``markers_of`` names the segment whose markers swept about the centre.
    """
    turn = f"rotation of {child} about its joint with {parent}"
    swept = f"{sweep:.1f} deg RMS" if np.isfinite(sweep) else "unknown"
    if sweep < MIN_EXERCISE_DEG:
        return f"needs {turn}: the recording barely turns it (sweep {swept})"
    if loose == 1 and radial**2 >= _RADIAL:
        return (
            f"needs a larger range of {turn}: the recorded sweep ({swept}) is too short an arc to fix how far "
            f"the centre lies from the markers of {markers_of}"
        )
    if loose == 1 and radial**2 <= 1.0 - _RADIAL:
        return (
            f"needs {turn} in more directions: the recorded sweep ({swept}) turns it mainly about one axis, "
            "along which the centre can slide"
        )
    return (
        f"needs {turn} over a larger range and in more directions: the recorded sweep ({swept}) leaves the centre "
        f"loose along {'two directions' if loose >= 2 else 'a direction neither along nor across its markers'}"
    )


def undetermined_lines(joints: Sequence[int], names: Sequence[str], skeleton: Any) -> list[str]:
    """The undetermined ``joints`` of a fitted ``skeleton`` (its segments ``names``), one line
    each with the motion that would fix it, between a heading and the advice (empty without
    joints)."""
    if not len(joints):
        return []
    from ..joints import loose_directions, radial_share

    edges = np.asarray(skeleton.edges)
    anchored = skeleton.diagnostics.get("anchored") or {}
    sweep = np.asarray(anchored.get("exercise", np.full(len(edges), np.nan)), float)
    anchor = np.asarray(anchored.get("anchor", np.full(len(edges), -1)), int)
    radial, loose = radial_share(skeleton), loose_directions(skeleton)
    lines = [
        f"{_WORD}: the recording fixes these centres only to within more than "
        f"{1000 * UNDETERMINED_RESOLUTION:.0f} mm (the distance along which the fit's misfit doubles), so they "
        "and the bones ending at them are as uncertain; each needs motion the recording lacks:"
    ]
    for j in joints:
        p, c = (int(v) for v in edges[j])
        swept = p if anchor[j] == c else c  # the segment whose markers swept about the centre
        why = missing_motion(names[p], names[c], sweep[j], radial[j], int(loose[j]), names[swept])
        lines.append(f"  {names[p]}-{names[c]}: {why}")
    lines.append(
        "Where they matter, fit the recording together with a range-of-motion trial of the same subject that has "
        "this motion (several inputs to fit_skeleton or jaxskel fit)"
    )
    return lines


def _how_chosen(topology: Any, n_segments: int, settings: Mapping[str, Any]) -> str:
    """The tree line: spanning tree, attachments, pose check, root."""
    spanning = "tree" if len(topology.edges) == n_segments - 1 else "forest"
    attached = len(getattr(topology, "attachments", ()))
    core = "of the joint costs"
    if attached:
        core += f" between segments of two or more markers, {attached} one-marker segment(s) hung from the most rigid"
    exchanges = len(topology.pose_exchanges)
    if exchanges:
        check = f"then {exchanges} joint(s) exchanged by the pose check (below)"
    elif settings.get("pose_check", True):
        check = "the pose check exchanged none"
    else:
        check = "no pose check"
    rooted = "at its centre" if settings.get("root") is None else "as given"
    return f"tree: minimum spanning {spanning} {core}, {check}; rooted {rooted}"


def tree_lines(topology: Any, names: Sequence[str], settings: Mapping[str, Any], segmentation: Any = None) -> list[str]:
    """How the tree was chosen, and its runner-up (module docstring). With ``segmentation``
    the runner-up is judged on the costs the core's tree was built on (attachments left
    out); without it on the joint costs."""
    from ..joints import core_costs, runner_up

    lines = [_how_chosen(topology, len(names), settings)]
    best = runner_up(topology, None if segmentation is None else core_costs(topology.pair_costs, segmentation))
    if best is None:
        lines.append("  runner-up: none (no joint chosen by cost has another feasible pair across its cut)")
        return lines
    (p, c), (a, b) = best.edge, best.rival
    lines.append(
        f"  runner-up: {names[a]}-{names[b]} instead of {names[p]}-{names[c]}, MST weight {100 * best.margin:+.1f} % "
        f"({1e6 * best.rival_cost:.3f} against {1e6 * best.cost:.3f} mm^2): the smallest margin of any joint over "
        "the cheapest other pair across its cut"
        + (" (below zero: the pose check jointed the dearer pair)" if best.margin < 0 else "")
    )
    return lines


def nonrigid_group_texts(seg: Segmentation, names: Sequence[str]) -> list[str]:
    """One line per segment whose markers move relative to each other (:meth:`Segmentation.nonrigid_groups`)."""
    return [
        f"segment {names[g]} is not rigid: {a} and {b} move relative to each other "
        f"(distance std {1e3 * std:.1f} mm, rigidity limit {1e3 * seg.rigid_limit:.1f} mm)"
        for g, a, b, std in seg.nonrigid_groups()
    ]


def nonrigid_group_hint(seg: Segmentation) -> str:
    """What to try when some segment's group is not rigid."""
    if seg.rigid_count:
        return (
            f"compare n_segments={seg.rigid_count} (--segments {seg.rigid_count}): the first larger count whose "
            "groups are all rigid, not chosen because it leaves a marker alone in a group"
        )
    return "two segments clustered as one, or a loose marker: consider a larger n_segments (--segments)"


def _hung_text(skeleton: Any, segment: int, names: Sequence[str]) -> str:
    """``; alone, ...``: how the joint of a one-marker segment was weighed in its host's pose
    (:mod:`jaxskel.skeleton._attachment_weights`), or ``""``."""
    if np.count_nonzero(np.asarray(skeleton.marker_segment) == segment) != 1:
        return ""
    scatter = np.asarray(skeleton.diagnostics.get("attachment_scatter", ()), dtype=float)
    weight = np.asarray(skeleton.diagnostics.get("attachment_weight", ()), dtype=float)
    edges = np.asarray(skeleton.edges)
    for j in np.flatnonzero(np.isfinite(scatter)) if scatter.size == len(edges) else ():
        if segment in edges[j]:
            host = int(edges[j, 0] if edges[j, 1] == segment else edges[j, 1])
            return (f"; alone on its segment, hung from {names[host]}: its joint wanders {1e3 * scatter[j]:.1f} mm "
                    f"there and steers that segment's pose with weight {weight[j]:.2g}")
    return ""


def nonrigid_text(skeleton: Any, names: Sequence[str], n_segments: int) -> str | None:
    """One line on the markers the rigid skeleton flags as not rigid, or ``None``."""
    if not skeleton.nonrigid_markers:
        return None
    labels = list(skeleton.marker_labels)
    where = [labels.index(lab) for lab in skeleton.nonrigid_markers]
    items = ", ".join(
        f"{labels[i]} on {names[int(skeleton.marker_segment[i])]} ({1e3 * skeleton.marker_rms[i]:.1f} mm"
        f"{_hung_text(skeleton, int(skeleton.marker_segment[i]), names)})"
        for i in where
    )
    return (
        f"not rigid on their segment: {items}; the rigid skeleton's residual RMS, against a median of "
        f"{1e3 * np.nanmedian(skeleton.marker_rms):.1f} mm. Soft tissue, a marker on a joint, or two segments "
        f"clustered as one: compare n_segments={n_segments + 1} (--segments)"
    )


def untested_text(u: Any, names: Sequence[str], sizes: np.ndarray) -> str:
    """One line on an :class:`jaxskel.joints.UntestedJoint`."""
    count = int(sizes[u.segment] + sizes[u.untested])
    return (
        f"  untested: {names[u.segment]} is jointed to {names[u.jointed_to]} but moves more rigidly with "
        f"{names[u.untested]} (median distance std {1e3 * u.std_untested:.1f} vs {1e3 * u.std_jointed:.1f} mm); "
        f"their {count} markers are too few to test a joint (4 needed): add a marker or check this joint"
    )


def near_tie_text(tie: Any, names: Sequence[str]) -> str:
    """One line on a :class:`jaxskel.joints.NearTie`."""
    (p, c), (a, b) = tie.edge, tie.rival
    return (
        f"near tie: {names[p]}-{names[c]} ({1e6 * tie.cost:.3f} mm^2) against {names[a]}-{names[b]} "
        f"({1e6 * tie.rival_cost:.3f} mm^2, {100 * tie.margin:+.1f} %, within the costs' sampling noise of "
        f"{100 * tie.noise:.1f} %): the tree could joint either"
    )


def pose_exchange_text(exchange: Any, names: Sequence[str]) -> str:
    """One line on a :class:`jaxskel.joints.PoseExchange`."""
    (a, b), (p, c) = exchange.added, exchange.removed
    (m_removed, m_added), (c_removed, c_added) = exchange.misfit, exchange.cost
    how = {  # PoseExchange.test
        "fixed": "a centre fixed in both segments fits",
        "sphere": "one segment's markers about a centre fixed in the other's pose fit",
        "near_tie": "the joint costs within their sampling noise, a centre fixed in both segments fits",
    }.get(getattr(exchange, "test", "fixed"), "the poses fit")
    return (
        f"pose check: {names[a]}-{names[b]} jointed instead of {names[p]}-{names[c]}: {how} {1e6 * m_added:.1f} "
        f"against {1e6 * m_removed:.1f} mm^2 (joint costs {1e6 * c_added:.3f} against {1e6 * c_removed:.3f} mm^2)"
    )
