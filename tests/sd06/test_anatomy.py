"""Knees and elbows from the skeleton's shape, and their one axis (issue 47: CMU's right elbow and knee).

Ground truth: synthetic humans (``synth.full_body``: elbows and knees are hinges; wrists,
ankles universal; the rest ball joints) and random trees, whose joint types are known.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
from calibration_motions import rotvec_to_matrix
from sd06_truth import protocol_and_free

from jaxskel import InputError, synth
from jaxskel._math.rotation import matrix_to_quat
from jaxskel.sd06 import normalize_arrays, parameterize_arrays, write_parameters
from jaxskel.sd06._anatomy import BONE_MATCH, limb_candidates, limb_hinges
from jaxskel.sd06._normalize import leaf_lengths_from_markers
from jaxskel.sd06._parameterize import parameterize_normalized

RATE = 30.0


def _normalized(body, seed: int = 0, duration: float = 3.0, **kw):
    _, truth = synth.simulate(body, "calibration", duration=duration, rate=RATE, seed=seed)
    quats = np.asarray(matrix_to_quat(truth.segment_rotations))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return normalize_arrays(truth.joint_positions, truth.edges, quats, root=truth.root, **kw), truth


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_knees_and_elbows_of_a_human_are_found(seed):
    body = synth.full_body(seed=seed)
    norm, _ = _normalized(body, seed=seed)
    names = np.array(body.joint_names)
    assert names[limb_hinges(norm)].tolist() == ["l_elbow", "l_knee", "r_elbow", "r_knee"]
    assert np.all(np.array(body.joint_types)[limb_hinges(norm)] == "hinge")


#: Trees of 6 to 9 segments by default, the larger ones (about 5 s each on 2 cores) with ``-m extended``.
@pytest.mark.parametrize("seed", [pytest.param(seed, marks=[pytest.mark.extended] if seed >= 4 else [])
                                  for seed in range(12)])
def test_random_trees_flag_only_mirrored_pairs(seed):
    """Whatever a random tree flags comes in pairs hanging from one segment whose spans agree."""
    body = synth.random_tree(6 + seed, seed=seed)
    norm, _ = _normalized(body, seed=seed, duration=1.5)
    hinge = limb_hinges(norm)
    bone_in, bone_out, hangs = limb_candidates(norm)
    span = bone_in + bone_out
    for j in np.flatnonzero(hinge):
        mates = [k for k in np.flatnonzero(hinge) if k != j and hangs[k] == hangs[j]
                 and abs(span[k] - span[j]) <= BONE_MATCH * max(span[k], span[j])]
        assert mates, (seed, j)


# ------------------------------------------------------------------ a hand-built human
#: Segments: 0 pelvis (root), 1-3 left thigh, shank, foot, 4-6 right, 7 thorax, 8-9 left
#: upper arm, forearm (a leaf), 10-11 right, 12 head. Joints j = child segment - 1.
_PARENT = [None, 0, 1, 2, 0, 4, 5, 0, 7, 8, 7, 10, 7]
_BONE = {1: 0.42, 2: 0.40, 4: 0.42, 5: 0.40, 7: 0.45, 8: 0.30, 10: 0.30}  # proximal -> distal joint
_LEAF = {3: 0.20, 6: 0.20, 9: 0.27, 11: 0.27, 12: 0.22}  # farthest marker


def _built(bone=None, leaf=None, extra=()):
    """A duck-typed normalisation of a straight human (limbs along -z in their own frames):
    ``edges``, ``root``, ``joint_offsets`` and ``leaf_lengths``; ``extra`` adds (parent,
    bone, leaf) limbs of two segments."""
    bone, leaf = {**_BONE, **(bone or {})}, {**_LEAF, **(leaf or {})}
    parent = list(_PARENT)
    for p, b, lf in extra:
        parent += [p, len(parent)]
        bone[len(parent) - 2], leaf[len(parent) - 1] = b, lf
    edges = np.array([[parent[c], c] for c in range(1, len(parent))])
    offsets = np.zeros((len(edges), 2, 3))
    for j, (p, _) in enumerate(edges):
        # at the parent's far end; the pelvis' and thorax' joints spread sideways
        offsets[j, 0] = [0.0, 0.1 * (j % 3), 0.0] if p in (0, 7) else [0.0, 0.0, -bone.get(p, 0.25)]
    lengths = np.array([leaf.get(s, 0.0) if s not in edges[:, 0] else 0.0 for s in range(len(parent))])
    return SimpleNamespace(edges=edges, root=0, joint_offsets=offsets, leaf_lengths=lengths)


def _found(norm):
    return (np.flatnonzero(limb_hinges(norm)) + 1).tolist()  # as child segments


def test_hand_built_human_knees_and_elbows():
    assert _found(_built()) == [2, 5, 9, 11]  # knees (shanks), elbows (forearms)


def test_partners_must_agree_in_length():
    """A right shank 0.7 m long: the legs' spans (0.82, 1.12 m) differ by 27 %, over
    BONE_MATCH, so neither knee is a hinge; at 0.5 m (spans 11 % apart) both are."""
    assert _found(_built(bone={5: 0.7})) == [9, 11]
    assert _found(_built(bone={5: 0.5})) == [2, 5, 9, 11]


def test_partners_choose_each_other():
    """A third leg on the pelvis (thigh 0.43 m, then a shank leaf whose farthest marker is
    0.42 m away: span 0.85 m, 4 % longer than the others): all three are within BONE_MATCH
    of each other, but the two equal legs choose each other and the third is left out.
    Made equal to them, it still finds no partner of its own: one pair per limb kind."""
    third = _built(extra=[(0, 0.43, 0.42)])
    bone_in, bone_out, hangs = limb_candidates(third)
    assert hangs[13] == hangs[1] == hangs[4] == 0  # three candidates on the pelvis
    np.testing.assert_allclose((bone_in + bone_out)[[1, 4, 13]], [0.82, 0.82, 0.85])
    assert _found(third) == [2, 5, 9, 11]
    assert _found(_built(extra=[(0, 0.42, 0.40)])) == [2, 5, 9, 11]


def test_an_unmeasured_forearm_leaf_or_a_branching_hand_hides_the_elbows():
    assert _found(_built(leaf={9: 0.0, 11: 0.0})) == [2, 5]
    # fingers: each forearm carries two two-segment fingers, so the arm ends in a branching
    # segment (no elbow); the fingers pair with each other (their middle joints are hinges too)
    found = _found(_built(extra=[(9, 0.05, 0.03), (9, 0.05, 0.03), (11, 0.05, 0.03), (11, 0.05, 0.03)]))
    assert found == [2, 5, 14, 16, 18, 20]


def test_leaf_lengths_from_markers():
    """A leaf's farthest marker from its proximal joint (in its own coordinates); NaN markers
    are skipped, a leaf without markers or with an unknown joint has no length (0)."""
    edges = np.array([[0, 1], [1, 2], [0, 3]])  # 2 and 3 are leaves
    seg = np.array([0, 2, 2, 2, 1])
    off = np.array([[0, 0, 0], [0, 0, -0.1], [0.03, 0, -0.2], [np.nan, 0, 9.0], [0, 0, 0.5]], float)
    joints = np.zeros((3, 2, 3))
    joints[1, 1] = [0.0, 0.0, 0.05]  # joint 1 in segment 2
    lengths = leaf_lengths_from_markers(edges, 0, seg, off, joints)
    np.testing.assert_allclose(lengths, [0.0, 0.0, np.hypot(0.03, 0.25), 0.0])
    joints[1, 1] = np.nan
    np.testing.assert_allclose(leaf_lengths_from_markers(edges, 0, seg, off, joints), 0.0)
    with pytest.raises(InputError, match="differ in length"):
        leaf_lengths_from_markers(edges, 0, seg[:-1], off)


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
