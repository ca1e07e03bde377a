"""Reference rigid skeleton (Kirk et al. 2005, §3.3) in numpy: per-segment Procrustes.

Each segment's points are its markers and its joints (the tree joints per frame).
A generalised Procrustes analysis per segment (Horn/Kabsch by SVD, vectorised over
frames, a few rounds of "align every frame to the mean shape, re-average") gives the
segment's constant local shape: marker offsets and joint offsets in that segment's
frame. Bone lengths are distances between two joints of one segment in its frame.

jaxskel then refines all offsets globally (alternating IK and a linear offset
solve); this reference stops at the Procrustes average, which is what a scientist
writing the method in a day would do. Its accuracy is reported next to jaxskel's.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["RefSkeleton", "kabsch", "fit_rigid"]


@dataclasses.dataclass
class RefSkeleton:
    """Segment tree with constant offsets; frames: origin at the proximal joint (root: centroid)."""

    edges: np.ndarray  # (J, 2) parent -> child
    root: int
    marker_segment: np.ndarray  # (M,)
    marker_offsets: np.ndarray  # (M, 3) in the segment frame (NaN if unused)
    joint_offsets: np.ndarray  # (J, 2, 3) in parent / child frame
    bones: np.ndarray  # (B, 2) joint index pairs on one segment
    bone_lengths: np.ndarray  # (B,)
    bone_segment: np.ndarray  # (B,)

    @property
    def n_segments(self) -> int:
        return len(self.edges) + 1


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid alignment per batch item: R (..., 3, 3), t (..., 3) with R src + t ~ dst."""
    wn = w / np.maximum(w.sum(-1, keepdims=True), 1e-300)
    mu_s = np.einsum("...n,...ni->...i", wn, src)
    mu_t = np.einsum("...n,...ni->...i", wn, dst)
    cov = np.einsum("...n,...ni,...nj->...ij", wn, dst - mu_t[..., None, :], src - mu_s[..., None, :])
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    rot = u @ vt
    return rot, mu_t - np.einsum("...ij,...j->...i", rot, mu_s)


def _segment_shape(pts: np.ndarray, pres: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Mean local shape (P, 3) of points ``pts`` (F, P, 3) present where ``pres`` (F, P)."""
    ok = pres.sum(1) >= 3
    pts, pres = pts[ok], pres[ok]
    w = pres.astype(float)
    ref = pts[np.argmax(pres.sum(1))]
    for _ in range(rounds):
        # align every frame onto the current reference shape (points present in both)
        ref_ok = np.isfinite(ref).all(1)
        ww = w * ref_ok[None]
        rot, t = kabsch(np.where(pres[..., None], pts, 0.0), np.nan_to_num(ref)[None].repeat(len(pts), 0), ww)
        moved = np.einsum("fij,fpj->fpi", rot, pts) + t[:, None]
        count = w.sum(0)
        ref = np.where(count[:, None] > 0, (moved * w[..., None]).sum(0) / np.maximum(count, 1)[:, None], np.nan)
    return ref


def fit_rigid(
    x: np.ndarray,
    mask: np.ndarray,
    seg: np.ndarray,
    edges: np.ndarray,
    root: int,
    joints: np.ndarray,
    *,
    max_frames: int = 1000,
) -> RefSkeleton:
    """Procrustes skeleton from markers ``x`` (F, M, 3) and joint centres ``joints`` (F, J, 3)."""
    n_seg = len(edges) + 1
    frames = np.unique(np.linspace(0, x.shape[0] - 1, min(max_frames, x.shape[0])).astype(int))
    x, mask, joints = x[frames], mask[frames], joints[frames]
    jok = np.isfinite(joints).all(-1)
    marker_offsets = np.full((x.shape[1], 3), np.nan)
    joint_offsets = np.zeros((len(edges), 2, 3))
    local_joint: dict[tuple[int, int], np.ndarray] = {}
    for s in range(n_seg):
        members = np.flatnonzero(seg == s)
        sj = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
        pts = np.concatenate([x[:, members], np.nan_to_num(joints[:, sj])], 1)
        pres = np.concatenate([mask[:, members], jok[:, sj]], 1)
        shape = _segment_shape(pts, pres)
        proximal = [j for j in sj if edges[j, 1] == s]
        if proximal:
            origin = shape[len(members) + list(sj).index(proximal[0])]
        else:
            origin = np.nanmean(shape[: len(members)], 0)
        shape = shape - origin
        marker_offsets[members] = shape[: len(members)]
        for i, j in enumerate(sj):
            local_joint[(s, j)] = shape[len(members) + i]
            joint_offsets[j, 0 if edges[j, 0] == s else 1] = shape[len(members) + i]
    bones, lengths, bone_seg = [], [], []
    for s in range(n_seg):
        sj = np.flatnonzero((edges[:, 0] == s) | (edges[:, 1] == s))
        for a in range(len(sj)):
            for b in range(a + 1, len(sj)):
                bones.append((sj[a], sj[b]))
                lengths.append(float(np.linalg.norm(local_joint[(s, sj[a])] - local_joint[(s, sj[b])])))
                bone_seg.append(s)
    return RefSkeleton(
        edges=np.asarray(edges), root=int(root), marker_segment=np.asarray(seg),
        marker_offsets=marker_offsets, joint_offsets=joint_offsets,
        bones=np.asarray(bones, int).reshape(-1, 2), bone_lengths=np.asarray(lengths),
        bone_segment=np.asarray(bone_seg, int),
    )
