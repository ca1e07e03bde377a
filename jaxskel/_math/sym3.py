"""Symmetric 3x3 blocks as six component arrays ("planes").

A symmetric matrix is the tuple ``(s00, s01, s02, s11, s12, s22)`` of arrays of one
batch shape, a vector the tuple of its three components. Every operation is
elementwise over the batch, so XLA vectorises it along the arrays' minor axis (the
batched IK keeps frames on the last axis, the joint solver's LM on the first) instead
of a minor axis of 3.
"""

from __future__ import annotations

__all__ = ["SYM", "UPPER", "sym_apply", "sym_inverse"]

#: (i, j) of each stored component: the upper triangle, row by row.
UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: ``SYM[i][j]``: the component holding entry (i, j).
SYM = ((0, 1, 2), (1, 3, 4), (2, 4, 5))


def sym_apply(s, v):
    """``S v``; the components of ``s`` must broadcast against those of ``v``."""
    return tuple(s[SYM[i][0]] * v[0] + s[SYM[i][1]] * v[1] + s[SYM[i][2]] * v[2] for i in range(3))


def sym_inverse(s):
    """Inverse of non-singular symmetric blocks: adjugate over determinant (cofactors)."""
    a, b, c, d, e, f = s
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    r = 1.0 / (a * c00 + b * c01 + c * c02)
    return (c00 * r, c01 * r, c02 * r, c11 * r, c12 * r, c22 * r)
