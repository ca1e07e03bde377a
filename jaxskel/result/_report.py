"""The text summary of a fit (:meth:`jaxskel.SkeletonResult.summary`), from the line
builders of :mod:`jaxskel.result._summary`. ``result`` is a :class:`jaxskel.SkeletonResult`
(not imported: the result imports this module)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ._summary import (
    bone_bound, is_loose, near_tie_text, nonrigid_group_hint, nonrigid_group_texts, nonrigid_text,
    pose_exchange_text, resolution_cell, tree_lines, undetermined_lines, untested_text,
)

__all__ = ["summary_text"]


def summary_text(result: Any) -> str:
    """Segments with their markers, joints with their costs, how the tree was chosen and
    its runner-up, bone lengths. A joint the recording fixes only to within more than
    10 cm reads ``undetermined``, with the motion that would fix it, and so does the
    bound of a bone ending at it (:mod:`jaxskel.result._summary`)."""
    lines = [f"{result.n_segments} segments, {len(result.edges)} joints, root {result.segment_names[result.topology.root]}"]
    lines += _body_lines(result.anatomy)
    seg = result.segmentation
    gaps = ", ".join(f"{k} ({gap:.3f})" for k, gap in seg.count_candidates())
    rule = {
        "given": "given",
        "eigengap": "eigengap",
        "rigid": f"grown from the eigengap's {seg.eigengap_segments} until every group is rigid "
        f"(A_ij <= {1e3 * seg.rigid_limit:.1f} mm)",
        "most rigid": f"grown from the eigengap's {seg.eigengap_segments} to the count whose least rigid group is "
        "the most rigid, "
        + (f"short of the first count with every group rigid ({seg.rigid_count}), which leaves a marker alone"
           if seg.rigid_count else f"as no count up to {seg.max_segments} has every group rigid"),
        "split": f"grown from {seg.split_from} (automatic) because one rigid body could not hold "
        f"{', '.join(seg.split_markers)} with the rest of their group (two or more in one group, by the group's "
        f"scatter or the rigid skeleton); compare n_segments={seg.split_from}",
    }[seg.count_rule]
    if seg.passed_joint_markers:
        moves = "; ".join(f"{joint} to the lone {lone}, {partner} to its nearest rigid group"
                          for joint, lone, partner in seg.passed_joint_markers)
        rule += (f", less {len(seg.passed_joint_markers)} where a marker on a joint left its group of two for a "
                 f"lone marker ({moves})")
    lines.append(
        f"segment count: {rule}; largest eigengaps after k = {gaps}; "
        f"white noise {1e3 * seg.white_noise:.2f} mm (taken out of A)"
    )
    groups = nonrigid_group_texts(seg, result.segment_names)
    if groups:
        lines += [f"  {text}" for text in groups] + [f"  {nonrigid_group_hint(seg)}"]
    if result.cleaning is not None and result.cleaning.duplicates:
        pairs = ", ".join(f"{a} -> {b}" for a, b in result.cleaning.duplicates.items())
        lines.append(f"duplicate labels merged (one marker stored twice): {pairs}")
    width = max(map(len, result.segment_names), default=0)
    for name, group in zip(result.segment_names, result.segmentation.groups):
        lines.append(f"  {name:>{width}}: {', '.join(group)}")
    if seg.still_spans:
        rate = result.trial.rate
        spans = ", ".join(f"{a / rate:.2f}-{b / rate:.2f} s" for a, b in seg.still_spans)
        lines.append(f"still trials ({spans}): no two segments move there, so they place markers on segments and "
                     "enter the skeleton and the motion, but not the joints")
    if seg.left_out:
        lines.append(f"left out of the skeleton ({len(seg.left_out)} marker(s) the motion cannot place):")
        lines += [f"  {label}: {why}" for label, why in seg.left_out.items()]
    anchored = (result.skeleton.diagnostics.get("anchored") if result.skeleton is not None else None) or {}
    resolution = result.joint_resolutions()
    lines += _joint_lines(result, anchored, resolution)
    lines += tree_lines(result.topology, result.segment_names, result.settings, result.segmentation)
    loose = [j for j in range(len(result.edges)) if is_loose(resolution[j])]
    if loose:
        lines += [f"  {line}" for line in undetermined_lines(loose, result.segment_names, result.skeleton)]
    for u in result.untested_joints():
        lines.append(untested_text(u, result.segment_names, result.segmentation.segment_sizes))
    for exchange in result.topology.pose_exchanges:
        lines.append(f"  {pose_exchange_text(exchange, result.segment_names)}")
    for tie in result.near_ties():
        lines.append(f"  {near_tie_text(tie, result.segment_names)}")
    nonrigid = nonrigid_text(result.skeleton, result.segment_names, result.n_segments) if result.skeleton else None
    if nonrigid is not None:
        lines.append(f"  {nonrigid}")
    unplaced = result.skeleton.diagnostics.get("unplaced_markers", ()) if result.skeleton else ()
    if unplaced:
        lines.append(f"  left out of the skeleton: {', '.join(unplaced)}, never seen in a frame with the other markers "
                     "and joints of their segment, so nothing places them on it")
    lines += _bone_lines(result, resolution)
    if result.motion is not None:
        rms = np.asarray(result.motion.marker_rms)
        lines.append(f"IK marker residual RMS: median {np.nanmedian(rms) * 1000:.2f} mm, max {np.nanmax(rms) * 1000:.2f} mm")
        cutoff = result.motion.lowpass_hz
        if cutoff is not None:
            done = cutoff[np.isfinite(cutoff)]
            lines.append(
                f"IK markers low-passed at {np.min(done):.1f}-{np.max(done):.1f} Hz (median {np.median(done):.1f}), "
                f"{len(cutoff) - len(done)} of {len(cutoff)} as measured"
                if len(done) else f"IK markers as measured (no white noise to filter in any of {len(cutoff)})"
            )
    return "\n".join(lines)

def _body_lines(anatomy: Any) -> list[str]:
    """The summary's named-body line (none where the fit did not name the body)."""
    if anatomy is None:
        return []
    if not anatomy.humanoid:
        return ["body: not human, so the segments keep their markers' names"
                + (f" ({anatomy.notes[0]})" if anatomy.notes else "")]
    named = [c for p, c in zip(anatomy.parts, anatomy.confidence) if p]
    low = f", confidence {min(named):.2f}-{max(named):.2f}" if named else ""
    return [f"body: human, {len(named)} of {len(anatomy.parts)} segments named{low}; "
            f"up {_direction(anatomy.up)}, facing {_direction(anatomy.front)} at the rest pose"]


def _direction(v: Any) -> str:
    """A unit vector in words: its nearest signed axis (``+z``) and how far it leans from it."""
    v = np.asarray(v, float)
    k = int(np.argmax(np.abs(v)))
    lean = np.degrees(np.arccos(min(1.0, abs(v[k]) / max(np.linalg.norm(v), 1e-12))))
    return f"{'+-'[int(v[k] < 0)]}{'xyz'[k]}" + (f" ({lean:.0f} deg off)" if lean >= 10 else "")


def _joint_lines(result: Any, anchored: dict[str, Any], resolution: np.ndarray) -> list[str]:
    """The summary's joints table: cost, uncertainty, steps, converged, sweep, resolution."""
    from ..joints import MIN_EXERCISE_DEG

    sweep = np.asarray(anchored.get("exercise", np.full(len(result.edges), np.nan)))
    names = [result.joint_name(j) for j in range(len(result.edges))]
    width = max(map(len, names), default=0)
    t = result.topology
    lines = ["joints (anatomical or parent-child): cost [mm^2], uncertainty [mm], steps, converged, sweep [deg], resolution [mm]"]
    for j, name in enumerate(names):
        lines.append(
            f"  {name:>{width}}: {t.joint_cost[j] * 1e6:9.3f}  {t.uncertainty[j] * 1000:7.1f}  "
            f"{int(t.steps[j]):5d}  {bool(t.converged[j])!s:5}  {sweep[j]:6.1f}  {resolution_cell(resolution[j])}"
            + ("  not exercised" if sweep[j] < MIN_EXERCISE_DEG else "")
        )
    placement = (result.skeleton.diagnostics.get("hinge_placement") if result.skeleton is not None else None) or []
    placed = [(names[j], how) for j, how in enumerate(placement) if how]
    if placed:
        lines.append("  hinge centres (the motion leaves each free along its axis) placed "
                     + "; ".join(f"{name}: {'in the plane of its neighbouring joints' if how == 'limb plane' else how}"
                                 for name, how in placed))
    return lines

def _bone_lines(result: Any, resolution: np.ndarray) -> list[str]:
    """The summary's bone table: lengths, and bounds where the rigid skeleton has them."""
    bones = result.bone_lengths()
    if not bones:
        return []
    if result.skeleton is None:
        return ["bone lengths [m]:"] + [f"  {name}: {length:.4f}" for name, length in bones.items()]
    from ..joints import bone_uncertainty

    loose = any(is_loose(resolution[j]) for j in np.ravel(result.skeleton.bones))
    lines = [
        "bone lengths [m], bound [mm] (how far its joints' resolutions let each length move; >= where one "
        f"joint's is unknown{', undetermined where one joint is' if loose else ''}):"
    ]
    spread = bone_uncertainty(result.skeleton)
    for (j0, j1), bound in zip(result.skeleton.bones, spread):
        name = result.bone_name(j0, j1)
        lines.append(f"  {name}: {bones[name]:.4f}  {bone_bound((j0, j1), resolution, bound, result.joint_name)}")
    return lines
