"""The number of movement axes per joint holds under marker noise (issue 47, item 3).

Markers from ``synth.simulate(..., noise=sigma)`` (Gaussian, per axis) at 0-3 mm;
the segments are posed from the noisy markers with the true skeleton (a
least-squares rigid fit per segment, top-down, each child also held at the joint
centre its parent places), and the axis count is compared with the truth: a
hinge has one axis; a ball or universal joint two; except the ankle, whose
second (inversion) axis is the foot's own heel -> toe long axis, so that the
foot only twists about it: one swing axis, the inversion is the twist. The count is
checked with the defaults (knees and elbows one axis from the anatomy) and from the
noise-corrected test alone (``axis_count="data"``).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import matrix_to_quat

from jaxskel import synth
from jaxskel.sd06 import parameterize

BODY = synth.full_body(seed=0)
RATE = 60.0


def _kabsch(local: np.ndarray, world: np.ndarray, weights: np.ndarray):
    """Per frame the rotation R and translation t with ``world ~ R local + t`` (weighted least squares)."""
    w = weights / weights.sum()
    cl = w @ local
    cw = np.einsum("m,fmk->fk", w, world)
    h = np.einsum("m,mi,fmj->fij", w, local - cl, world - cw[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
    fix = np.ones((len(d), 3))
    fix[:, 2] = d
    rot = np.swapaxes(vt, 1, 2) @ (fix[:, :, None] * np.swapaxes(u, 1, 2))
    return rot, cw - np.einsum("fij,j->fi", rot, cl)


def posed_from_markers(trial, truth):
    """Segment poses, quaternions and joint centres fitted to the trial's (noisy) markers."""
    x = np.asarray(trial.positions)[:, truth.physical]
    seg, off = truth.marker_segment[truth.physical], truth.marker_offsets[truth.physical]
    n_f, n_s = x.shape[0], truth.n_segments
    rot, trans = np.zeros((n_f, n_s, 3, 3)), np.zeros((n_f, n_s, 3))
    rot[:, truth.root], trans[:, truth.root] = _kabsch(off[seg == truth.root], x[:, seg == truth.root], np.ones((seg == truth.root).sum()))
    joints = np.zeros((n_f, truth.edges.shape[0], 3))
    for j in BODY.joint_order:
        parent, child = truth.edges[j]
        joints[:, j] = np.einsum("fik,k->fi", rot[:, parent], truth.joint_offsets[j, 0]) + trans[:, parent]
        mine = seg == child
        local = np.concatenate([off[mine], truth.joint_offsets[j, 1][None]])
        world = np.concatenate([x[:, mine], joints[:, j, None]], axis=1)
        rot[:, child], trans[:, child] = _kabsch(local, world, np.r_[np.ones(mine.sum()), 4.0])
    return joints, np.asarray(matrix_to_quat(rot)), trans


@pytest.mark.parametrize("noise_mm", [0.0, 1.0, 2.0, 3.0])
def test_axis_count_is_right_for_every_joint_at_every_noise_level(noise_mm):
    trial, truth = synth.simulate(BODY, "calibration", duration=20.0, rate=RATE, seed=3, noise=noise_mm / 1000.0)
    joints, quats, trans = posed_from_markers(trial, truth)
    skeleton = SimpleNamespace(
        edges=truth.edges, root=truth.root, marker_segment=truth.marker_segment, marker_offsets=truth.marker_offsets,
        joint_offsets=truth.joint_offsets,
    )
    motion = SimpleNamespace(joint_positions=joints, rotations=quats, segment_translations=trans, rate=RATE)
    param = parameterize(skeleton, motion)
    kind = np.array(BODY.joint_types)
    ankle = np.array(["ankle" in n for n in BODY.joint_names])
    expected = np.where((kind == "hinge") | ankle, 1, 2)
    detail = dict(zip(BODY.joint_names, np.degrees(param.hinge_rms).round(2).tolist(), strict=True))
    np.testing.assert_array_equal(param.n_axes, expected, err_msg=f"{noise_mm} mm; one-axis RMS (deg) {detail}")
    np.testing.assert_array_equal(param.axis_count_source == "anatomy", kind == "hinge")
    # The noise model alone (no anatomy) counts every joint right too, the hinges included.
    data = parameterize(skeleton, motion, param.normalization, axis_count="data")
    np.testing.assert_array_equal(data.n_axes, expected, err_msg=f"{noise_mm} mm, axis_count='data'; {detail}")
    # The noise estimate follows the markers: zero without noise, growing with it.
    if noise_mm == 0:
        assert np.degrees(param.noise).max() < 0.1
    else:
        assert np.degrees(np.median(param.noise)) > 0.2 * noise_mm
