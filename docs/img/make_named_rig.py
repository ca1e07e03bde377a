"""Draw the README's figure of the named, T-posed rig: the BVH that ``jaxskel demo`` writes,
read back with ``jaxskel.result.read_bvh``, its rest pose seen from the front (Y up, the
subject's left on +X), every joint labelled with its BVH name.

Usage: ``jaxskel demo -o /tmp/demo && python docs/img/make_named_rig.py /tmp/demo/skeleton.bvh docs/img/named_rig.png``
"""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxskel.result import read_bvh  # noqa: E402


def rest_positions(data) -> np.ndarray:
    """(S, 3) joint positions at rest (every channel zero): offsets summed down the tree."""
    out = np.zeros((len(data.names), 3))
    for s, p in enumerate(np.asarray(data.parents).tolist()):  # parents precede children in a BVH
        out[s] = (out[p] if p >= 0 else 0.0) + np.asarray(data.offsets[s])
    return out


def main(bvh: str, png: str) -> None:
    data = read_bvh(bvh)
    rest = rest_positions(data)
    fig, ax = plt.subplots(figsize=(5.2, 6.0))
    for s, p in enumerate(np.asarray(data.parents).tolist()):
        if p >= 0:
            ax.plot(rest[[p, s], 0], rest[[p, s], 1], "-", color="0.35", lw=2)
    ax.plot(rest[:, 0], rest[:, 1], "o", color="tab:blue", ms=5)
    for name, (x, y, _) in zip(data.names, rest):
        ax.annotate(name, (x, y), xytext=(4, 3), textcoords="offset points", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("X: the subject's left (cm)")
    ax.set_ylabel("Y: up (cm)")
    ax.set_title("jaxskel demo: skeleton.bvh at rest (T-pose, Mixamo names)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=120)


if __name__ == "__main__":
    main(*sys.argv[1:3])
