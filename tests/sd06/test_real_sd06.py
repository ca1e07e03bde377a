"""SD06 on a real recording: CMU 02_05's elbows and knees (issue 47), against references that
do not come from SD06 (``bench/sd06_cmu.py`` reports the same comparison in full)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from human_markers import segment_parts

import jaxskel

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "nimblephysics" / "cmu_02_05.c3d"

pytestmark = [
    pytest.mark.extended,  # a full fit (~1 min) and a parameterisation of a real take
    pytest.mark.skipif(not DATA.is_file(), reason=f"real recording not found at {DATA}"),
]


def _angle_at(mid, above, below):
    u, v = above - mid, below - mid
    cos = np.sum(u * v, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
    return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def test_cmu_elbows_and_knees_are_hinges_that_follow_their_flexion():
    """With the defaults the knees and elbows (found from the skeleton's shape) get one axis,
    and their angle follows the flexion: the elbows the joint-centre angle (shoulder - elbow -
    wrist markers), the knees the skin markers' angle (thigh - knee - ankle markers; the
    fitted right hip is too far from the knee to be a reference)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = jaxskel.fit_skeleton(jaxskel.load(DATA))
        param = jaxskel.sd06.parameterize(res.skeleton, res.motion)
    parts = segment_parts(res.trial.labels, res.segmentation.marker_segment)
    joint = {frozenset((parts[p], parts[c])): j for j, (p, c) in enumerate(res.skeleton.edges.tolist())}
    labels = [str(x).upper() for x in res.trial.labels]
    raw = np.where(res.trial.mask[..., None], res.trial.positions, np.nan)

    def marker(name):
        return raw[:, next(i for i, x in enumerate(labels) if x.endswith(name))]

    centres = res.motion.joint_positions
    hinges = []
    for s in "RL":
        elbow = joint[frozenset((f"{s} upper arm", f"{s} forearm"))]
        shoulder = joint[frozenset(("thorax", f"{s} upper arm"))]
        wrist = 0.5 * (marker(f"{s}WRA") + marker(f"{s}WRB"))
        knee = joint[frozenset((f"{s} thigh", f"{s} shank"))]
        hinges += [
            (elbow, _angle_at(centres[:, elbow], centres[:, shoulder], wrist)),
            (knee, _angle_at(marker(f"{s}KNE"), marker(f"{s}THI"), marker(f"{s}ANK"))),
        ]
    found = sorted(j for j, _ in hinges)
    assert np.flatnonzero(param.axis_count_source == "anatomy").tolist() == found
    assert np.all(param.n_axes[found] == 1)
    for j, reference in hinges:
        seen = np.isfinite(reference)
        corr = abs(np.corrcoef(param.angles[seen, j, 0], reference[seen])[0, 1])
        assert corr > 0.99, (j, corr)


@pytest.mark.parametrize("take", ["KneeltoProne01.c3d", "PronetoRun01.c3d"])
def test_takes_that_lie_down_normalise_on_a_standing_frame(take):
    """Both takes have the subject lying prone, a flat and elongated pose that the default-pose
    cost favours; the default pose is taken among the frames whose body plane stands."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trial = jaxskel.load(DATA.parents[1] / "auto_marker_label" / take)
        res = jaxskel.fit_skeleton(trial)
        norm = jaxskel.sd06.normalize(res.skeleton, res.motion, up_axis=trial.up_axis)
    assert abs(norm.body_frame[:, 0] @ norm.up) < np.sin(np.radians(60.0))  # the frontal normal is not up
    lying = [f for f in range(norm.n_frames) if norm.cost[f] < norm.cost[norm.default_frame]]
    assert lying  # a flatter frame exists: the subject lying down
