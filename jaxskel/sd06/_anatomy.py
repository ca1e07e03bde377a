"""Which joints are a limb's hinge (knee, elbow), from the skeleton's shape alone.

Sar Dessai et al. (2006, §4) extract "the movement axes corresponding to the degrees of
freedom described in [Kea05]": how many axes a joint has depends on "the type of the
parent joint" (one for a forearm that is "flexed and extended"), and only the axes'
directions come from the data. The knee and the elbow (humero-ulnar joint) have one
degree of freedom besides the limb's twist. This module finds them without names, so
that their axis count can follow the anatomy where the data alone is misled (soft tissue
turning a two-marker thigh or upper arm about its long axis swings the hinge's plane by
tens of degrees: ``docs/bench/sd06_cmu.md``).

Definitions, from the tree and the constant bone lengths of the normalised skeleton:

* **limb**: the joints from a branching segment (one with two or more distal joints, or
  the root: a pelvis, a thorax) out to a leaf, through segments with one distal joint
  each: hip, knee, ankle; shoulder, elbow, wrist. A chain that ends in another branching
  segment (the spine) is not a limb.
* **bones** of joint k: in, from the proximal joint of k's parent segment to k (the
  thigh for a knee); out, from k to its child segment's distal joint or, for a leaf
  child, to the leaf's farthest marker (``Normalization.leaf_lengths``; unknown: none).
* **candidate**: in each limb, of the joints after the first, the one joining the two
  longest consecutive bones, the largest ``min(in, out)``: the knee (thigh, shank), not
  the ankle (foot); the elbow (upper arm, forearm), not the wrist (hand) nor, where a
  clavicle segment starts the limb, the shoulder.
* **hinge**: a candidate that has a mirror partner: the candidate of another limb that
  hangs from the same branching segment and whose two bones together are as long as its
  own, to within :data:`BONE_MATCH`; partners choose each other (the least relative
  difference). The sum, not each bone, is compared because a fitted hinge centre may sit
  a few centimetres up or down its limb. Legs pair with legs (pelvis) and arms with arms
  (thorax); a neck and head chain, which has no partner, never holds a hinge. Which side
  of the body a limb is on is not used: on real takes the limbs' mean positions are
  asymmetric, and the body frame of a recording without a held default pose does not
  tell left from right reliably enough. A body with two similar limbs on one side of one
  segment (not a human) would have them taken as a pair.
* **not found**: an arm whose hand segment branches (fingers and thumb) ends in a
  branching segment and so is not a limb; a limb whose leaf length is unknown (no
  markers) has no out bone there.

A joint found this way gets one axis unless the caller gives its count
(``axis_count="anatomy"``, the default of :func:`~jaxskel.sd06.parameterize`); with
``axis_count="data"`` every joint's count comes from the data.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

from ._normalize import Normalization, tree_arrays

__all__ = ["AXIS_COUNTS", "BONE_MATCH", "limb_hinges", "limb_candidates"]

#: Where a joint's axis count comes from when ``n_axes`` does not give it.
AXIS_COUNTS = ("anatomy", "data")

#: Largest relative difference between two mirror partners' bones (in + out): the two
#: sides of a body agree to a few per cent (a fit to ~15 %: CMU 02_05's knees, elbows), a
#: leg (thigh + shank) and an arm (upper arm + forearm) differ by a third.
BONE_MATCH = 0.2


def limb_candidates(
    normalization: Normalization,
) -> tuple[Float[np.ndarray, " J"], Float[np.ndarray, " J"], Int[np.ndarray, " J"]]:
    """Per joint: the in and out bone lengths (metres), and for its limb's candidate the
    branching segment the limb hangs from (-1 for every other joint)."""
    norm = normalization
    edges = np.asarray(norm.edges)
    n_joints = edges.shape[0]
    tree = tree_arrays(edges, norm.root)
    leaf_len = np.zeros(n_joints + 1) if norm.leaf_lengths is None else np.asarray(norm.leaf_lengths)
    offsets = np.asarray(norm.joint_offsets)
    prev = tree.chain_proximal
    bone_in = np.where(prev >= 0, np.linalg.norm(offsets[:, 0] - offsets[np.maximum(prev, 0), 1], axis=1), 0.0)
    child = edges[:, 1]
    distal_centroid = tree.chain_distal @ offsets[:, 0]  # in the child's limb frame
    bone_out = np.where(
        tree.leaf[child], leaf_len[child], np.linalg.norm(distal_centroid - offsets[:, 1], axis=1)
    )
    n_distal = np.bincount(edges[:, 0], minlength=n_joints + 1)
    branching = (n_distal >= 2) | (np.arange(n_joints + 1) == norm.root)
    hangs_from = np.full(n_joints, -1)
    for start in np.flatnonzero(branching[edges[:, 0]]):
        chain = [int(start)]
        while n_distal[child[chain[-1]]] == 1:
            chain.append(int(np.flatnonzero(edges[:, 0] == child[chain[-1]])[0]))
        if not tree.leaf[child[chain[-1]]] or len(chain) < 2:
            continue  # ends in a branching segment (a spine), or has no joint after its first
        inner = np.asarray(chain[1:])
        score = np.minimum(bone_in[inner], bone_out[inner])
        if score.max() > 0:
            hangs_from[inner[np.argmax(score)]] = edges[start, 0]
    return bone_in, bone_out, hangs_from


def limb_hinges(normalization: Normalization) -> Bool[np.ndarray, " J"]:
    """(J,) True for the knees and elbows of :class:`Normalization`'s skeleton (module docstring).

    Where ``normalization.leaf_lengths`` is None, a hinge whose child is a leaf (a forearm
    without a hand segment) is not found.
    """
    bone_in, bone_out, hangs_from = limb_candidates(normalization)
    idx = np.flatnonzero(hangs_from >= 0)
    hinge = np.zeros(hangs_from.size, bool)
    if idx.size < 2:
        return hinge
    span = bone_in[idx] + bone_out[idx]
    mismatch = np.abs(span[:, None] - span[None]) / np.maximum(span[:, None], span[None])
    mismatch[hangs_from[idx, None] != hangs_from[None, idx]] = np.inf  # partners hang from one segment
    np.fill_diagonal(mismatch, np.inf)
    best = np.argmin(mismatch, axis=1)
    rows = np.arange(idx.size)
    mutual = (best[best] == rows) & (mismatch[rows, best] <= BONE_MATCH)
    hinge[idx[mutual]] = True
    return hinge
