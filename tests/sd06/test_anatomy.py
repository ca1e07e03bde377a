"""Knees and elbows from the skeleton's shape, and their one axis (issue 47: CMU's right elbow and knee).

Ground truth: synthetic humans (``synth.full_body``: elbows and knees are hinges; wrists,
ankles universal; the rest ball joints) and random trees, whose joint types are known.
"""

from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest
from calibration_motions import rotvec_to_matrix
from sd06_truth import protocol_and_free

from jaxskel import InputError, synth
from jaxskel._math.rotation import matrix_to_quat
from jaxskel.sd06 import normalize_arrays, parameterize_arrays, write_parameters
from jaxskel.sd06._anatomy import BONE_MATCH, limb_candidates, limb_hinges
from jaxskel.sd06._parameterize import parameterize_normalized

RATE = 30.0


def _normalized(body, seed: int = 0, duration: float = 3.0, **kw):
    _, truth = synth.simulate(body, "calibration", duration=duration, rate=RATE, seed=seed)
    quats = np.asarray(matrix_to_quat(truth.segment_rotations))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return normalize_arrays(truth.joint_positions, truth.edges, quats, root=truth.root, **kw), truth


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_the_knees_and_elbows_of_a_human_are_found(seed):
    body = synth.full_body(seed=seed)
    norm, _ = _normalized(body, seed=seed)
    names = np.array(body.joint_names)
    assert names[limb_hinges(norm)].tolist() == ["l_elbow", "l_knee", "r_elbow", "r_knee"]
    assert np.all(np.array(body.joint_types)[limb_hinges(norm)] == "hinge")


def test_random_trees_have_no_limb_hinges_that_are_not_hinges():
    """Random trees rarely hold two mirrored limbs; where one is flagged, it must be a hinge
    (measured: none of 40 trees' 404 joints flagged wrongly)."""
    wrong = 0
    for seed in range(12):
        body = synth.random_tree(6 + seed, seed=seed)
        norm, _ = _normalized(body, seed=seed, duration=1.5)
        wrong += int(np.sum(limb_hinges(norm) & (np.array(body.joint_types) != "hinge")))
    assert wrong == 0


def _without(body, cut):
    """The human's arrays with the segments ``cut`` (and their joints) removed."""
    _, truth = synth.simulate(body, "calibration", duration=3.0, rate=RATE, seed=1)
    names = list(body.segment_names)
    gone = [names.index(n) for n in cut]
    keep_seg = [s for s in range(len(names)) if s not in gone]
    keep_joint = [j for j, (p, c) in enumerate(body.edges) if c not in gone]
    remap = {s: i for i, s in enumerate(keep_seg)}
    edges = np.array([[remap[p], remap[c]] for p, c in body.edges[keep_joint]])
    quats = np.asarray(matrix_to_quat(truth.segment_rotations))[:, keep_seg]
    joints = truth.joint_positions[:, keep_joint]
    return joints, edges, quats, remap[body.root], remap, np.array(body.joint_names)[keep_joint]


def test_a_forearm_without_a_hand_is_measured_by_its_markers():
    """The elbow's out bone is then the forearm leaf's length, which only its markers give."""
    body = synth.full_body(seed=0)
    joints, edges, quats, root, remap, names = _without(body, ("l_hand", "r_hand"))
    forearms = [remap[list(body.segment_names).index(n)] for n in ("l_forearm", "r_forearm")]
    lengths = np.zeros(edges.shape[0] + 1)
    lengths[forearms] = 0.27  # elbow to the farthest wrist marker
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bare = normalize_arrays(joints, edges, quats, root=root)
        measured = normalize_arrays(joints, edges, quats, root=root, leaf_lengths=lengths)
    assert names[limb_hinges(bare)].tolist() == ["l_knee", "r_knee"]
    assert names[limb_hinges(measured)].tolist() == ["l_elbow", "l_knee", "r_elbow", "r_knee"]
    bone_in, bone_out, _ = limb_candidates(measured)
    elbows = [names.tolist().index(n) for n in ("l_elbow", "r_elbow")]
    np.testing.assert_allclose(bone_out[elbows], 0.27)
    with pytest.raises(InputError, match="leaf_lengths"):
        normalize_arrays(joints, edges, quats, root=root, leaf_lengths=lengths[:-1])


def test_a_lone_limb_or_unequal_limbs_hold_no_hinge():
    """A hinge needs a mirror partner: the one leg left has none (a leg and an arm hang
    from different segments and differ by more than the tolerance)."""
    body = synth.full_body(seed=0)
    joints, edges, quats, root, _, names = _without(body, ("l_thigh", "l_shank", "l_foot"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        norm = normalize_arrays(joints, edges, quats, root=root)
    assert names[limb_hinges(norm)].tolist() == ["l_elbow", "r_elbow"]
    bone_in, bone_out, hangs = limb_candidates(norm)
    knee, elbow = names.tolist().index("r_knee"), names.tolist().index("l_elbow")
    assert hangs[knee] >= 0 and hangs[elbow] >= 0 and hangs[knee] != hangs[elbow]
    leg, arm = bone_in[knee] + bone_out[knee], bone_in[elbow] + bone_out[elbow]
    assert (leg - arm) / leg > BONE_MATCH


# ------------------------------------------------------------------ the one axis on real-like data
def _soft_tissue_session(amplitude_deg: float = 15.0):
    """Protocol + free movement, with the left upper arm and the right thigh spinning about
    their own long axis by +-amplitude (slowly), as soft tissue turns a two-marker segment:
    the joints stay where they are, the parent's frame turns, and the hinge's plane with it."""
    body = synth.full_body(seed=0)
    rec = protocol_and_free(body, free_seconds=20.0, seed=0)
    rot = rec.rot.copy()
    t = np.arange(rot.shape[0]) / RATE
    names, segs = list(body.joint_names), list(body.segment_names)
    for seg, joint in (("l_upperarm", "l_elbow"), ("r_thigh", "r_knee")):
        s, j = segs.index(seg), names.index(joint)
        proximal = body.edges[:, 1].tolist().index(s)
        axis = rec.joints[:, j] - rec.joints[:, proximal]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        spin = np.radians(amplitude_deg) * np.sin(2 * np.pi * t / 7.0 + s)
        rot[:, s] = rotvec_to_matrix(axis * spin[:, None]) @ rot[:, s]
    return body, rec, np.asarray(matrix_to_quat(rot))


@pytest.fixture(scope="module")
def soft_tissue():
    body, rec, quats = _soft_tissue_session()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        anatomy = parameterize_arrays(rec.joints, body.edges, quats, root=body.root, calibration=rec.protocol)
        data = parameterize_normalized(anatomy.normalization, calibration=rec.protocol, axis_count="data")
    return body, rec, anatomy, data


def _flexion_error_deg(param, rec, j):
    est, truth = param.angles[:, j, 0], rec.angles[j][:, 0]
    sign = np.sign(np.corrcoef(est, truth)[0, 1])
    return float(np.degrees(np.sqrt(np.mean((sign * est - truth) ** 2))))


def test_a_spinning_thigh_keeps_the_knee_one_axis_and_its_flexion(soft_tissue):
    """The data alone gives the spun knee two axes and a first angle that is not its flexion;
    the anatomy keeps one axis, and the flexion follows the generator's to ~0.5 degrees."""
    body, rec, anatomy, data = soft_tissue
    names = list(body.joint_names)
    knee = names.index("r_knee")
    assert data.n_axes[knee] == 2 and data.axis_count_source[knee] == "data"
    assert _flexion_error_deg(data, rec, knee) > 20.0
    hinges = np.array(body.joint_types) == "hinge"
    np.testing.assert_array_equal(anatomy.n_axes[hinges], 1)
    assert set(anatomy.axis_count_source[hinges]) == {"anatomy"}
    assert set(anatomy.axis_count_source[~hinges]) == {"data"}
    for joint in ("r_knee", "l_elbow", "l_knee", "r_elbow"):
        assert _flexion_error_deg(anatomy, rec, names.index(joint)) < 1.5, joint
    # the other joints' counts do not depend on the knees' and elbows'
    np.testing.assert_array_equal(anatomy.n_axes[~hinges], data.n_axes[~hinges])
    assert data.settings["axis_count"] == "data" and anatomy.settings["axis_count"] == "anatomy"


def test_a_given_count_overrides_the_anatomy(soft_tissue, tmp_path):
    body, rec, anatomy, _ = soft_tissue
    knee = list(body.joint_names).index("r_knee")
    given = parameterize_normalized(anatomy.normalization, calibration=rec.protocol, n_axes={knee: 2})
    assert given.n_axes[knee] == 2 and given.axis_count_source[knee] == "given"
    assert given.settings["n_axes"][knee] == 2 and sum(given.settings["n_axes"]) == 2
    with pytest.raises(InputError, match="axis_count"):
        parameterize_normalized(anatomy.normalization, axis_count="names")
    with h5py.File(tmp_path / "p.h5", "w") as f:
        write_parameters(f.create_group("parameters"), given)
    with h5py.File(tmp_path / "p.h5") as f:
        assert f["parameters/axis_count_source"].asstr()[knee] == "given"
        assert f["parameters"].attrs["axis_count"] == "anatomy"
