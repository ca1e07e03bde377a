"""Figures of a fitted skeleton (matplotlib, no display needed).

* :func:`plot_distance_std` — the distance std-dev matrix A ordered by group:
  dark diagonal blocks are rigid segments.

Segments are labelled by ``result.segment_names`` (readable names from their markers,
:mod:`jaxskel.segment._names`) and joints ``parent-child`` from them.
* :func:`plot_spectrum` — the affinity spectrum behind the segment count (eigengap).
* :func:`plot_joint_costs` — the all-pairs joint-cost matrix with the tree's
  edges marked.
* :func:`plot_skeleton_3d` — markers coloured by segment, joints and bones at one frame.
* :func:`plot_residuals` — IK marker residual RMS over time.
* :func:`plot_summary` — all five in one figure, saved atomically.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

__all__ = ["plot_distance_std", "plot_spectrum", "plot_joint_costs", "plot_skeleton_3d", "plot_residuals", "plot_summary"]


def _plt():
    import matplotlib

    if os.environ.get("MPLBACKEND") is None and matplotlib.get_backend().lower() not in ("agg", "module://matplotlib_inline.backend_inline"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _ax(ax: Any, projection: str | None = None) -> Any:
    if ax is not None:
        return ax
    plt = _plt()
    fig = plt.figure(figsize=(6, 5))
    return fig.add_subplot(111, projection=projection)


def plot_distance_std(result: Any, ax: Any = None) -> Any:
    """Distance std-dev matrix (mm) with markers ordered by segment, each segment's block
    named along the top."""
    ax = _ax(ax)
    seg = result.segmentation
    order = np.argsort(seg.marker_segment, kind="stable")
    a = seg.distance_std[np.ix_(order, order)] * 1000
    im = ax.imshow(a, cmap="viridis", vmax=np.nanpercentile(a, 95))
    ax.figure.colorbar(im, ax=ax, label="std of distance [mm]")
    labels = [seg.labels[i] for i in order]
    ax.set_xticks(range(len(labels)), labels, rotation=90, fontsize=5)
    ax.set_yticks(range(len(labels)), labels, fontsize=5)
    bounds = np.flatnonzero(np.diff(seg.marker_segment[order])) + 0.5
    for b in bounds:
        ax.axhline(b, color="w", lw=0.6)
        ax.axvline(b, color="w", lw=0.6)
    ordered = seg.marker_segment[order]
    shown = [s for s in range(seg.n_segments) if (ordered == s).any()]
    top = ax.secondary_xaxis("top")
    top.set_xticks([np.flatnonzero(ordered == s).mean() for s in shown],
                   [result.segment_names[s] for s in shown], rotation=90, fontsize=5)
    ax.set_title("marker distance std-dev, by segment")
    return ax


def plot_spectrum(result: Any, ax: Any = None) -> Any:
    """Eigenvalues of the normalised affinity behind the segment count, with the
    eigengap's choice and the count used marked."""
    ax = _ax(ax)
    seg = result.segmentation
    ev = np.asarray(seg.eigenvalues)
    k = np.arange(1, len(ev) + 1)
    ax.plot(k, ev, "o-", ms=3, lw=0.8)
    best = seg.count_candidates()
    for rank, (kk, gap) in enumerate(best):
        ax.annotate(f"{gap:.3f}", (kk + 0.5, 0.5 * (ev[kk - 1] + ev[kk])), fontsize=7,
                    color="C1" if rank == 0 else "0.4")
    ax.axvline(seg.eigengap_segments + 0.5, color="C1", lw=1, label=f"eigengap: {seg.eigengap_segments}")
    if seg.n_segments != seg.eigengap_segments:
        how = {"rigid": "grown until rigid", "most rigid": "grown to the most rigid",
               "split": "grown after the rigid fit"}.get(seg.count_rule, seg.count_rule)
        if seg.passed_joint_markers:
            how += f", less {len(seg.passed_joint_markers)}: joint markers passed"
        ax.axvline(seg.n_segments + 0.5, color="C2", lw=1, ls="--", label=f"used: {seg.n_segments} ({how})")
    ax.set_xlabel("k")
    ax.set_ylabel("eigenvalue of the normalised affinity")
    ax.legend(fontsize=7)
    ax.set_title("segment count (numbers: the largest gaps)")
    return ax


def plot_joint_costs(result: Any, ax: Any = None) -> Any:
    """All-pairs joint cost (log10 of mm^2) with tree edges circled."""
    ax = _ax(ax)
    cost = result.topology.pair_costs.cost * 1e6
    with np.errstate(divide="ignore"):
        shown = np.where(np.isfinite(cost), np.log10(np.maximum(cost, 1e-12)), np.nan)
    im = ax.imshow(shown, cmap="magma_r")
    ax.figure.colorbar(im, ax=ax, label="log10 joint cost [mm^2]")
    for p, c in result.topology.edges:
        for u, v in ((p, c), (c, p)):
            ax.scatter([v], [u], s=60, facecolors="none", edgecolors="c", linewidths=1.5)
    names = list(result.segment_names)
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=6)
    ax.set_yticks(range(len(names)), names, fontsize=6)
    ax.set_title("joint costs (circles: tree)")
    return ax


def _best_frame(result: Any) -> int:
    present = result.trial.mask.sum(axis=1) + np.isfinite(result.joint_positions[..., 0]).sum(axis=1)
    return int(np.argmax(present))


def plot_skeleton_3d(result: Any, frame: int | None = None, ax: Any = None) -> Any:
    """Markers (coloured by segment), joint centres and bones at one frame."""
    ax = _ax(ax, projection="3d")
    frame = _best_frame(result) if frame is None else int(frame)
    x = result.trial.positions[frame]
    seg = result.segmentation.marker_segment
    plt = _plt()
    cmap = plt.get_cmap("tab20")
    for s in range(result.n_segments):
        pts = x[seg == s]
        pts = pts[np.isfinite(pts).all(axis=1)]  # the markers seen in this frame
        # one colour as a list: a bare RGBA tuple beside 2-4 points reads as one colour per point
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=12, color=[cmap(s % 20)], label=result.segment_names[s])
    jp = result.joint_positions[frame]
    ax.scatter(jp[:, 0], jp[:, 1], jp[:, 2], s=30, color="k", marker="x")
    if result.skeleton is not None:
        for j0, j1 in result.skeleton.bones:
            seg_pts = jp[[j0, j1]]
            ax.plot(seg_pts[:, 0], seg_pts[:, 1], seg_pts[:, 2], color="k", lw=1.5)
    else:
        edges = result.edges
        for s in range(result.n_segments):
            js = [j for j, (p, c) in enumerate(edges) if s in (p, c)]
            for a in js:
                for b in js:
                    if a < b:
                        ax.plot(*jp[[a, b]].T, color="k", lw=1.5)
    finite = np.concatenate([x[np.isfinite(x[:, 0])], jp[np.isfinite(jp[:, 0])]])
    if len(finite):
        centre = finite.mean(0)
        half = max(np.ptp(finite, axis=0).max() / 2, 0.1)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_title(f"markers, joints and bones at frame {frame}")
    ax.legend(fontsize=5, loc="upper left", ncol=2)
    return ax


def plot_residuals(result: Any, ax: Any = None) -> Any:
    """IK marker residual RMS (mm) per frame."""
    ax = _ax(ax)
    if result.motion is None:
        ax.text(0.5, 0.5, "no IK (rigid skeleton switched off)", ha="center", va="center")
        return ax
    rms = np.asarray(result.motion.marker_rms) * 1000
    t = np.arange(len(rms)) / result.trial.rate
    ax.plot(t, rms, lw=0.8)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("marker RMS [mm]")
    ax.set_title(f"IK residual (median {np.nanmedian(rms):.1f} mm)")
    return ax


def _tree_layout(n: int, edges: np.ndarray, roots: list[int]) -> dict[int, tuple[float, int]]:
    """(x, depth) of every segment: leaves spaced evenly in depth-first order, a parent
    centred over its children, roots at depth 0."""
    children: dict[int, list[int]] = {s: [] for s in range(n)}
    for p, c in np.asarray(edges, dtype=int).reshape(-1, 2).tolist():
        children[p].append(c)
    place: dict[int, tuple[float, int]] = {}
    next_leaf = [0.0]

    def visit(s: int, depth: int) -> float:
        kids = [visit(c, depth + 1) for c in children[s]]
        x = float(np.mean(kids)) if kids else next_leaf[0]
        if not kids:
            next_leaf[0] += 1.0
        place[s] = (x, depth)
        return x

    for r in roots:
        visit(int(r), 0)
    for s in range(n):  # a segment outside every tree (none in a fit): a row of its own
        if s not in place:
            place[s] = (next_leaf[0], 0)
            next_leaf[0] += 1.0
    return place


def plot_tree(result: Any, ax: Any = None) -> Any:
    """The fitted tree as a hierarchy from its root: segments by name, joints as lines,
    one-marker attachments in grey, joints the recording leaves undetermined dashed."""
    ax = _ax(ax)
    topo = result.topology
    names = list(result.segment_names)
    place = _tree_layout(result.n_segments, topo.edges, list(topo.roots))
    loose = {u.joint for u in result.undetermined_joints()}
    hung = {a.segment for a in getattr(topo, "attachments", ())}
    for j, (p, c) in enumerate(np.asarray(topo.edges, dtype=int).tolist()):
        (x0, y0), (x1, y1) = place[p], place[c]
        ax.plot([x0, x1], [-y0, -y1], color="0.6" if c in hung else "k", lw=1.2, ls="--" if j in loose else "-")
    for s, (x, y) in place.items():
        ax.text(x, -y, names[s], ha="center", va="center", fontsize=5, rotation=0 if len(names[s]) <= 8 else 20, color="0.45" if s in hung else "k",
                bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "0.6" if s in hung else "k", "lw": 0.6})
    xs = [x for x, _ in place.values()]
    depth = max((d for _, d in place.values()), default=0)
    ax.set_xlim(min(xs, default=0) - 1, max(xs, default=0) + 1)
    ax.set_ylim(-depth - 0.6, 0.6)
    ax.set_axis_off()
    ax.set_title("tree from the root (grey: one-marker attachments; dashed: undetermined joints)", fontsize=9)
    return ax


def plot_summary(result: Any, path: str | os.PathLike[str] | None = None, *, overwrite: bool = False) -> Any:
    """2 x 3 summary figure; saved atomically to ``path`` when given (its suffix, one of the
    image types matplotlib writes, picks the format; checked before the figure is drawn)."""
    if path is not None:
        from ..io import check_output, image_format

        fmt = image_format(check_output(path, "image"))
    plt = _plt()
    fig = plt.figure(figsize=(19, 11))
    plot_distance_std(result, fig.add_subplot(2, 3, 1))
    plot_spectrum(result, fig.add_subplot(2, 3, 2))
    plot_joint_costs(result, fig.add_subplot(2, 3, 3))
    plot_skeleton_3d(result, ax=fig.add_subplot(2, 3, 4, projection="3d"))
    plot_residuals(result, fig.add_subplot(2, 3, 5))
    plot_tree(result, fig.add_subplot(2, 3, 6))
    fig.suptitle(str(result.trial.source or "jaxskel fit"), fontsize=9)
    fig.tight_layout()
    if path is not None:
        from ..io import atomic_output

        with atomic_output(path, overwrite) as tmp:
            fig.savefig(tmp, dpi=110, format=fmt)
        plt.close(fig)
    return fig
