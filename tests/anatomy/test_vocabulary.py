"""The named body's vocabulary: one tree over the parts, joint and marker names for each, and the Anatomy record."""

from __future__ import annotations

import numpy as np
import pytest

import jaxskel
from jaxskel.anatomy import JOINT_OF_PART, PARENT_PART, PARTS, VIRTUAL_MARKER, Anatomy, joint_name, mirror, side_of


def test_the_parts_form_one_tree_rooted_at_the_pelvis():
    assert set(PARENT_PART) == set(PARTS)
    for part in PARTS:
        seen, p = set(), part
        while p:  # every chain ends at the pelvis, without a cycle
            assert p not in seen
            seen.add(p)
            p = PARENT_PART[p]
        assert "pelvis" in seen
    assert [p for p in PARTS if not PARENT_PART[p]] == ["pelvis"]


def test_sides_mirror_onto_each_other_and_the_tree_is_symmetric():
    for part in PARTS:
        assert mirror(mirror(part)) == part
        assert mirror(part) in PARTS
        assert side_of(mirror(part)) == {"l": "r", "r": "l", "": ""}[side_of(part)]
        assert PARENT_PART[mirror(part)] == mirror(PARENT_PART[part])
    assert side_of("pelvis") == "" and side_of("") == "" and mirror("") == ""


def test_every_joint_and_virtual_marker_name_is_distinct():
    assert set(JOINT_OF_PART) == set(PARTS) - {"pelvis"}
    assert len(set(JOINT_OF_PART.values())) == len(JOINT_OF_PART)
    assert set(VIRTUAL_MARKER) == set(JOINT_OF_PART.values())
    assert len(set(VIRTUAL_MARKER.values())) == len(VIRTUAL_MARKER)
    assert joint_name("shank_r") == "knee_r" and VIRTUAL_MARKER["knee_r"] == "RKJC"
    assert joint_name("pelvis") == "" and joint_name("") == ""


def test_an_anatomy_knows_left_and_rejects_unknown_parts():
    a = Anatomy(("pelvis", "thigh_l", ""), [0.9, 0.8, 0.0], True, up=[0, 0, 1], front=[1, 0, 0])
    np.testing.assert_array_equal(a.left, [0, 1, 0])  # up x front
    assert a.segment_of("thigh_l") == 1 and a.segment_of("thigh_r") is None
    with pytest.raises(jaxskel.InputError, match="unknown body parts"):
        Anatomy(("pelvis", "femur"), [1, 1], True, up=[0, 0, 1], front=[1, 0, 0])
    with pytest.raises(jaxskel.InputError, match="one value per segment"):
        Anatomy(("pelvis", "thigh_l"), [1], True, up=[0, 0, 1], front=[1, 0, 0])


def test_joints_are_named_after_the_distal_part_of_either_edge_direction():
    from jaxskel.anatomy import joint_between

    assert joint_between("thigh_l", "shank_l") == joint_between("shank_l", "thigh_l") == "knee_l"
    assert joint_between("pelvis", "thorax") == "thoracic"  # no abdomen segment between them
    assert joint_between("thorax", "upper_arm_r") == "shoulder_r"  # no clavicle segment
    assert joint_between("thigh_l", "thigh_r") == ""  # siblings: neither is proximal
    assert joint_between("shank_l", "") == ""


def test_an_anatomy_names_segments_and_joints_where_it_knows_the_parts():
    anatomy = Anatomy(parts=("pelvis", "thigh_r", "", "shank_r"), confidence=[1, 1, 0, 0.5], humanoid=True,
                      up=[0, 0, 1], front=[1, 0, 0])
    assert anatomy.segment_names(("W", "RTH", "X", "RSH")) == ("pelvis", "thigh_r", "X", "shank_r")
    edges = np.array([[0, 1], [3, 1], [0, 2]])  # a tree rooted at the shank orders the knee's edge distal-first
    assert anatomy.joint_names(edges, ("a", "b", "c")) == ("hip_r", "knee_r", "c")
    with pytest.raises(jaxskel.InputError, match="fallback"):
        anatomy.segment_names(("W",))


def test_segment_names_stay_distinct_when_a_part_names_two_segments():
    anatomy = Anatomy(parts=("hand_l", "hand_l", ""), confidence=[1, 0.5, 0], humanoid=True, up=[0, 0, 1],
                      front=[1, 0, 0])
    assert anatomy.segment_names(("LHA", "LFIN", "X")) == ("hand_l", "hand_l_2", "X")


def test_the_piece_in_the_chain_keeps_the_plain_name_when_a_part_names_two_segments():
    """A one-marker twig listed before its host, or the short end of a limb cut in two, is
    ``part_2``; the segment joined to the other parts of the tree is ``part``."""
    parts = ("thorax", "upper_arm_l", "upper_arm_l", "forearm_l")
    anatomy = Anatomy(parts=parts, confidence=[1, 0.5, 1, 1], humanoid=True, up=[0, 0, 1], front=[1, 0, 0])
    edges = np.array([[0, 2], [2, 1], [2, 3]])  # segment 1 hangs off segment 2, which the chain runs through
    np.testing.assert_array_equal(anatomy.main_segments(edges), [True, False, True, True])
    assert anatomy.segment_names(("T", "A", "B", "F"), edges) == ("thorax", "upper_arm_l_2", "upper_arm_l",
                                                                  "forearm_l")
    assert anatomy.segment_names(("T", "A", "B", "F")) == ("thorax", "upper_arm_l", "upper_arm_l_2", "forearm_l")
    from jaxskel.result._export_names import part_names

    assert part_names(anatomy, ("T", "A", "B", "F"), "mixamo", edges) == ("Spine", "LeftArm_2", "LeftArm",
                                                                         "LeftForeArm")
