"""Fragments: the contiguous runs of every label, the units that label merging joins.

A passive tracker gives a marker a new label after each occlusion and may reuse
a label slot for another marker later, so a label is not trusted across a gap,
nor across a jump no marker could make in one frame. Merging therefore works
on fragments; when no label needs cutting the fragments are the labels.
Host-side (numpy): one cheap pass over the data.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Bool, Float, Int

from .._errors import DegenerateMotionError

__all__ = ["Fragments", "split_fragments", "fragment_arrays", "chain_arrays", "check_continuity"]


@dataclasses.dataclass(frozen=True)
class Fragments:
    """Fragment k is label ``label[k]`` over frames ``[start[k], stop[k])``."""

    label: Int[np.ndarray, " K"]
    start: Int[np.ndarray, " K"]
    stop: Int[np.ndarray, " K"]

    @property
    def length(self) -> Int[np.ndarray, " K"]:
        return self.stop - self.start

    @property
    def size(self) -> int:
        return int(self.label.size)

    def cooccur(self) -> Bool[np.ndarray, "K K"]:
        """True where two fragments share a frame (the diagonal included)."""
        return (self.start[:, None] < self.stop[None, :]) & (self.start[None, :] < self.stop[:, None])


def split_fragments(
    present: Bool[np.ndarray, "F M"], x: Float[np.ndarray, "F M 3"], max_step: float
) -> Fragments:
    """Contiguous runs of every label, cut where it moves more than ``max_step`` in one frame.

    Sorted by label, then by start frame, so an uncut trial gives one fragment
    per label, in label order.
    """
    jump = np.zeros_like(present)
    jump[1:] = present[1:] & present[:-1] & (np.linalg.norm(x[1:] - x[:-1], axis=-1) > max_step)
    continues_from_prev = np.zeros_like(present)
    continues_from_prev[1:] = present[:-1] & ~jump[1:]
    continues_to_next = np.zeros_like(present)
    continues_to_next[:-1] = present[1:] & ~jump[1:]
    label, start = np.nonzero((present & ~continues_from_prev).T)
    _, last = np.nonzero((present & ~continues_to_next).T)
    return Fragments(label=label, start=start, stop=last + 1)


def fragment_arrays(
    x: Float[np.ndarray, "F M 3"], frags: Fragments
) -> tuple[Float[np.ndarray, "F K 3"], Bool[np.ndarray, "F K"]]:
    """Positions (zero where absent) and presence with one column per fragment."""
    frames = np.arange(x.shape[0])[:, None]
    inside = (frames >= frags.start[None]) & (frames < frags.stop[None])
    return np.where(inside[..., None], x[:, frags.label], 0.0), inside


def chain_arrays(
    xf: Float[np.ndarray, "F K 3"], mf: Bool[np.ndarray, "F K"], chain: Int[np.ndarray, " K"], n_columns: int
) -> tuple[Float[np.ndarray, "F C 3"], Bool[np.ndarray, "F C"]]:
    """Positions and presence with one column per chain (fragments of one marker; -1: none)."""
    frames, frag = np.nonzero(mf & (chain >= 0)[None, :])
    xc = np.zeros((mf.shape[0], n_columns, 3), dtype=xf.dtype)
    mc = np.zeros((mf.shape[0], n_columns), dtype=bool)
    xc[frames, chain[frag]] = xf[frames, frag]
    mc[frames, chain[frag]] = True
    return xc, mc


def check_continuity(present: Bool[np.ndarray, "F K"], rate: float, min_common: int) -> None:
    """Raise if some instant has fewer than ``min_common`` markers tracked through it.

    A fragment is one contiguous run, so the labels shared by a frame before t
    and a frame after t are tracked through t. With fewer than ``min_common``
    of them nothing can be aligned across t, and no label before t can be
    matched to one after it (the paper: "the method will fail if all markers
    are lost simultaneously"). Sparse frames at the very start or end are ignored.
    """
    count = present.sum(axis=1)
    usable = np.flatnonzero(count >= min_common)
    if usable.size == 0:
        raise DegenerateMotionError(
            f"no frame has {min_common} markers seen together (at most {count.max()}); merging labels "
            "aligns frames on shared markers and needs at least that many. Check the recording."
        )
    lo, hi = usable[0], usable[-1]
    through = (present[lo:hi] & present[lo + 1 : hi + 1]).sum(axis=1)
    broken = np.flatnonzero(through < min_common)
    if broken.size:
        f = int(lo + broken[0] + 1)
        later = np.flatnonzero(count[f:] >= min_common)
        resume = f + int(later[0]) if later.size else f
        raise DegenerateMotionError(
            f"at frame {f} (t = {f / rate:.3f} s) only {through[broken[0]]} markers are tracked "
            "continuously: the others are all lost at once, so no frame before can be aligned with "
            "one after and labels cannot be matched across (Kirk et al. §4). Merge the parts "
            f"separately, e.g. trial[:{f}] and trial[{resume}:]."
        )
