"""3-vectors and 3x3 matrices as tuples of component arrays ("planes").

A vector is the tuple ``(v0, v1, v2)`` of arrays of one batch shape, a general 3x3
matrix the 9-tuple of its entries row by row (``m[3 * i + j]`` is entry (i, j)), a
symmetric one the 6-tuple of its upper triangle (:data:`UPPER`, :data:`SYM`). Every
operation is elementwise over the batch, so XLA vectorises it along the arrays' minor
axis (the batched IK keeps frames on the last axis, the joint solver's LM on the first)
instead of a minor axis of 3. Components broadcast against each other, and plain
Python floats are accepted where an operation only scales or adds them.

The rotations in this layout (quaternions, the SO(3) Jacobian, Horn's alignment) are
in :mod:`jaxskel._math.rotation_planes`.
"""

from __future__ import annotations

__all__ = [
    "SYM",
    "UPPER",
    "cross_left",
    "cross_right",
    "mmul",
    "mtmul_sym",
    "mtvec",
    "mvec",
    "sym_apply",
    "sym_full",
    "sym_inverse",
    "sym_mul",
    "vadd",
    "vcross",
    "vdot",
    "vscale",
    "vsub",
]

#: (i, j) of each stored component of a symmetric matrix: the upper triangle, row by row.
UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
#: ``SYM[i][j]``: the component holding entry (i, j) of a symmetric matrix.
SYM = ((0, 1, 2), (1, 3, 4), (2, 4, 5))


# ------------------------------------------------------------------ vectors
def vadd(a, b):
    """``a + b`` componentwise (any equal-length tuples)."""
    return tuple(x + y for x, y in zip(a, b))


def vsub(a, b):
    """``a - b`` componentwise (any equal-length tuples)."""
    return tuple(x - y for x, y in zip(a, b))


def vscale(s, a):
    """``s a`` for a scalar (array) ``s`` and any tuple ``a``."""
    return tuple(s * x for x in a)


def vdot(a, b):
    """``a . b``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def vcross(a, b):
    """``a x b``."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


# ---------------------------------------------------------- general matrices
def mvec(m, v):
    """``M v``."""
    return tuple(m[3 * i] * v[0] + m[3 * i + 1] * v[1] + m[3 * i + 2] * v[2] for i in range(3))


def mtvec(m, v):
    """``M^T v``."""
    return tuple(m[j] * v[0] + m[3 + j] * v[1] + m[6 + j] * v[2] for j in range(3))


def mmul(a, b):
    """``A B``."""
    return tuple(
        a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j] for i in range(3) for j in range(3)
    )


def mtmul_sym(a, b):
    """Upper triangle of ``A^T B`` (for a product known to be symmetric)."""
    return tuple(a[i] * b[j] + a[3 + i] * b[3 + j] + a[6 + i] * b[6 + j] for i, j in UPPER)


def cross_right(m, r):
    """``M (-[r]x)``: column j of the product is ``M (e_j x r)``."""
    out = []
    for i in range(3):
        a0, a1, a2 = m[3 * i], m[3 * i + 1], m[3 * i + 2]
        out += [a2 * r[1] - a1 * r[2], a0 * r[2] - a2 * r[0], a1 * r[0] - a0 * r[1]]
    return tuple(out)


def cross_left(r, m):
    """``[r]x M``: column j of the product is ``r x M[:, j]``."""
    cols = [vcross(r, (m[j], m[3 + j], m[6 + j])) for j in range(3)]
    return tuple(cols[j][i] for i in range(3) for j in range(3))


# -------------------------------------------------------- symmetric matrices
def sym_full(s):
    """The general (9-tuple) form of a symmetric matrix."""
    return tuple(s[SYM[i][j]] for i in range(3) for j in range(3))


def sym_apply(s, v):
    """``S v``; the components of ``s`` must broadcast against those of ``v``."""
    return tuple(s[SYM[i][0]] * v[0] + s[SYM[i][1]] * v[1] + s[SYM[i][2]] * v[2] for i in range(3))


def sym_mul(s, m):
    """``S M``: symmetric (6-tuple) times general (9-tuple), a general matrix."""
    return tuple(
        s[SYM[i][0]] * m[j] + s[SYM[i][1]] * m[3 + j] + s[SYM[i][2]] * m[6 + j] for i in range(3) for j in range(3)
    )


def sym_inverse(s):
    """Inverse of non-singular symmetric matrices: adjugate over determinant (cofactors)."""
    a, b, c, d, e, f = s
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    r = 1.0 / (a * c00 + b * c01 + c * c02)
    return (c00 * r, c01 * r, c02 * r, c11 * r, c12 * r, c22 * r)
