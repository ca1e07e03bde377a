"""Skeletons fitted to real CMU / HDM05 recordings, judged against their .asf skeletons.

These recordings use the 41-marker Vicon set: one or two markers per limb segment,
several of them placed on joints (knee, ankle, elbow, wrist), which is far from the
marker clusters the method assumes. What is checked:

* the tree: every joint joins body parts that are adjacent in a human skeleton
  (parts named from the marker labels, :mod:`human_markers`);
* the limb bones (hip-knee, knee-ankle, shoulder-elbow, elbow-wrist joint distances)
  against the subject's .asf bones; the differences are printed (``pytest -s``). The
  issue's target is 2 cm; what is asserted is what the method reaches today on these
  recordings (see the README, "Known limits"), so that a regression fails.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from human_markers import (
    asf_bone_lengths,
    bone_index_by_part,
    implausible_edges,
    misplaced_markers,
    segment_parts,
)

import jaxskel

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real recordings not found at {DATA}")

#: Fitted limb bone -> the .asf bones it spans.
ASF_BONES = {"thigh": ("femur",), "shank": ("tibia",), "upper arm": ("humerus",), "forearm": ("radius", "wrist")}


def _fit(rel: str, n_segments: int | None):
    trial = jaxskel.load(DATA / rel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return jaxskel.fit_skeleton(trial, n_segments, ik=False)


def _compare(result, asf: Path) -> dict[str, tuple[float, float, float]]:
    """Fitted part -> (fitted, asf, bound) in metres, printed. ``bound`` is how far the
    bone's joints' resolutions let its length move (:func:`jaxskel.joints.bone_uncertainty`; a
    lower bound where a joint has none, e.g. a knee between two two-marker segments)."""
    reference = asf_bone_lengths(asf)
    bound = jaxskel.joints.bone_uncertainty(result.skeleton)
    out = {}
    for part, b in sorted(bone_index_by_part(result).items()):
        names = [part[0].lower() + bone for bone in ASF_BONES[part[2:]]]
        if all(name in reference for name in names):  # CMU's 02.asf keeps the legs only
            length = float(result.skeleton.bone_lengths[b])
            out[part] = (length, sum(reference[name] for name in names), float(bound[b]))
    print(f"\n{asf.name}: fitted vs .asf, and the fit's bound (mm)")
    for part, (fit, ref, spread) in out.items():
        print(f"  {part:12s} {1e3 * fit:6.0f} {1e3 * ref:6.0f}  {1e3 * (fit - ref):+6.0f}  {1e3 * spread:6.0f}")
    return out


def _within_target_or_bound(bones: dict[str, tuple[float, float, float]]) -> None:
    """Every bone within the issue's 2 cm of the .asf, or within the bound the fit gives
    it: a bone the recording cannot fix may miss, but never by more than the fit says."""
    for part, (fit, ref, spread) in bones.items():
        assert abs(fit - ref) < max(0.02, spread), (part, fit, ref, spread)


@pytest.fixture(scope="module")
def hdm_dg():
    return _fit("dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d", None)


def test_hdm05_tree_is_a_human_skeleton(hdm_dg):
    """HDM05 actor dg, 1.7 s, automatic segment count: 13 segments (pelvis, thorax, head,
    upper arms, forearms with hands, thighs, shanks, feet), every joint anatomical.

    The left heel and toe markers move apart (distance std 19 mm, 5.7 sigma: the toes
    bend), so the count would grow until the groups are rigid; the first rigid count, 15,
    leaves the heel marker alone, and with two or three markers on each neighbour no
    joint of it is feasible but far-off ones (it was jointed to the right forearm). The
    eigengap's 13 is kept and the non-rigid foot is reported."""
    # the file stores three markers twice, as unnamed *0, *1, *2: cleaning merges them
    assert hdm_dg.cleaning.duplicates == {"*0": "LFWT", "*1": "CLAV", "*2": "LFHD"}
    parts = segment_parts(hdm_dg.trial.labels, hdm_dg.segmentation.marker_segment)
    assert hdm_dg.n_segments == 13 and hdm_dg.segmentation.count_rule == "eigengap"
    ((_, first, second, _),) = hdm_dg.segmentation.nonrigid_groups()
    assert {first.split(":")[-1], second.split(":")[-1]} == {"LHEE", "LTOE"}
    assert "is not rigid" in hdm_dg.summary()
    assert hdm_dg.segmentation.rigid_count == 15 and "compare n_segments=15" in hdm_dg.summary()
    for limb in ("thigh", "shank", "foot", "upper arm", "forearm"):
        assert {f"L {limb}", f"R {limb}"} <= set(parts), (limb, parts)
    assert implausible_edges(hdm_dg.trial.labels, hdm_dg.segmentation.marker_segment, hdm_dg.edges) == []


def test_hdm05_limb_bones_against_asf(hdm_dg):
    """All six limb bones with both joints in the tree are measured. Today: left shank
    +6.5 mm, upper arms +11.0/+9.8 mm, right thigh +9.0 mm, right shank +18.6 mm (within
    the 2 cm target), left thigh +21.4 mm (joints of a 1.7 s take that are barely
    exercised, markers on the joints; the fit's bound on that bone is 79 mm). While the
    file's copies of LFWT, CLAV and LFHD counted twice (before duplicate labels were
    merged) the right shank was +21 and the left thigh +33 mm; with the paper's per-frame
    joint centres (``joint_centres="per_frame"``) the right thigh was +122 and the right
    shank +73 mm. Asserted (a regression guard, not the target): every bone within 2.5 cm,
    the sum of the six within 5 %, four bones within 2 cm, and every bone within 2 cm or
    within the bound the fit reports for it."""
    bones = _compare(hdm_dg, DATA / "dynamic_clustering_hdm05" / "HDM_dg.asf")
    assert {"L thigh", "R thigh", "L shank", "R shank", "L upper arm", "R upper arm"} <= set(bones)
    fit, ref, _ = np.array(list(bones.values())).T
    assert np.max(np.abs(fit - ref)) < 0.025, bones
    _within_target_or_bound(bones)
    assert abs(fit.sum() - ref.sum()) < 0.05 * ref.sum()
    assert sum(np.abs(fit - ref) < 0.02) >= 4


def test_flat_spectrum_grows_to_the_rigid_count_with_the_knee_marker_paired():
    """numediart 85_12 (CMU set, 37 s): the spectrum has no clear gap (8: 0.100, 9: 0.082,
    13: 0.073) and the eigengap's 8 segments join thighs, shanks and feet (five non-rigid
    groups, bones up to 1.3 m). The first rigid count, 13, puts the right knee marker with
    the shank and leaves the right thigh marker alone; the knee marker is as rigid with the
    thigh marker as with the shank (9.9 against 8.3 mm), so it goes to the thigh marker
    (``_pair_lone_markers``), no lone marker is left, and 13 is taken. Before, 8 was kept:
    4 implausible joints and 4 misplaced markers (``bench/real_trees.py``)."""
    trial, _ = jaxskel.clean.clean(jaxskel.load(DATA / "numediart" / "85_12.c3d"))
    seg = jaxskel.segment.segment_markers(trial)
    assert (seg.eigengap_segments, seg.count_rule, seg.n_segments) == (8, "rigid", 13)
    assert seg.nonrigid_groups() == []
    groups = {frozenset(g) for g in seg.groups}
    assert frozenset(("RTHI", "RKNE")) in groups and frozenset(("LTHI", "LKNE")) in groups
    assert all(len(g) >= 2 for g in seg.groups)


def test_short_take_whose_rigid_count_leaves_a_marker_alone_grows_to_the_most_rigid_count():
    """The first half of CMU 01_01 (11 s of walking): the eigengap's 5 groups hold the trunk,
    pelvis and both legs as one (whole legs against the pelvis: 8 misplaced markers in the
    default fit before, ``bench/real_trees.py --halves``). The first rigid count, 14, leaves a
    marker alone; 13, the most rigid count before it, leaves none and is taken: thigh,
    shank and foot of each leg apart, no marker with a part it is not on."""
    trial = jaxskel.load(DATA / "c3d_to_xyz_cmu" / "01_01.c3d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trial, _ = jaxskel.clean.clean(trial.select_frames(slice(0, trial.n_frames // 2)))
    seg = jaxskel.segment.segment_markers(trial)
    assert (seg.eigengap_segments, seg.count_rule, seg.n_segments, seg.rigid_count) == (5, "most rigid", 13, 14)
    assert misplaced_markers(trial.labels, seg.marker_segment, seg.distance_std, seg.rigid_limit) == []
    assert all(len(g) >= 2 for g in seg.groups)
    parts = segment_parts(trial.labels, seg.marker_segment)
    for side in "LR":
        legs = [parts.index(f"{side} {part}") for part in ("thigh", "shank", "foot")]
        assert len(set(legs)) == 3, parts


def test_an_elbow_marker_clustered_with_the_forearm_goes_to_the_lone_upper_arm_marker():
    """HDM05 bd (CMU set, 49 s): the eigengap's groups hold the left elbow marker with the
    forearm marker, a group of two, and leave the upper-arm marker alone. The elbow is about
    as rigid with the upper arm (8.0 mm) as with the forearm (5.9 mm) and the forearm marker
    as rigid with the wrist pair (4.0, 5.7 mm), so the elbow joins the upper arm and the
    forearm marker the wrist (``_pass_joint_marker``). Before, the lone upper-arm marker hung
    as a leaf and the trunk was jointed to the forearm (``bench/real_trees.py``)."""
    trial = jaxskel.load(DATA / "numediart" / "HDM_bd_05-01_01_120.c3d")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trial, _ = jaxskel.clean.clean(trial)
    seg = jaxskel.segment.segment_markers(trial)
    groups = {frozenset(g) for g in seg.groups}
    assert frozenset(("LUPA", "LELB")) in groups and frozenset(("LFRM", "LWRA", "LWRB")) in groups
    assert seg.passed_joint_markers == (("LELB", "LUPA", "LFRM"),)
    assert seg.n_segments == seg.eigengap_segments - 1 and seg.count_rule == "eigengap"
    assert seg.nonrigid_groups() == []
    assert misplaced_markers(trial.labels, seg.marker_segment, seg.distance_std, seg.rigid_limit) == []


@pytest.mark.extended  # about 90 s on 2 cores; the segmentation above runs by default
def test_the_passed_elbow_marker_gives_the_trunk_its_upper_arm_and_says_so(tmp_path):
    """HDM05 bd, the whole default fit: the trunk is jointed to the left upper arm and the upper
    arm to the forearm (the trunk was jointed to the forearm before); the summary and the
    result file say which joint marker was passed and why the count is one below the
    eigengap's."""
    result = _fit("numediart/HDM_bd_05-01_01_120.c3d", None)
    labels, seg = result.trial.labels, result.segmentation.marker_segment
    parts = segment_parts(labels, seg)
    edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist()}
    assert {frozenset(("thorax", "L upper arm")), frozenset(("L upper arm", "L forearm"))} <= edges
    assert not [e for e in implausible_edges(labels, seg, result.edges) if "L forearm" in e or "L upper arm" in e]
    assert "less 1 where a marker on a joint left its group of two for a lone marker (LELB to the lone LUPA" in (
        result.summary())
    path = tmp_path / "hdm.h5"
    result.save(str(path))
    with h5py.File(path, "r") as f:
        assert [[v.decode() for v in row] for row in f["segments/passed_joint_markers"][()]] == [["LELB", "LUPA", "LFRM"]]


@pytest.mark.extended  # about a minute on 2 cores; the segmentation above runs by default
def test_numediart_85_12_tree_is_anatomical_with_default_settings():
    """numediart 85_12 (CMU set, 37 s), the whole default fit on the 13 rigid segments: every
    joint joins adjacent body parts and no marker sits with a part it is not on. The ankle
    barely moves in this take, so the left heel marker stays with the shin and ankle markers;
    the map names that group the shank (its ankle marker breaks the shin-heel tie), and it
    is jointed to the left thigh and the left forefoot."""
    result = _fit("numediart/85_12.c3d", None)
    labels, seg = result.trial.labels, result.segmentation.marker_segment
    assert result.n_segments == 13
    assert implausible_edges(labels, seg, result.edges) == []
    assert misplaced_markers(labels, seg, result.segmentation.distance_std, result.segmentation.rigid_limit) == []
    parts = segment_parts(labels, seg)
    edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist()}
    for s in "LR":
        assert {frozenset(("pelvis", f"{s} thigh")), frozenset((f"{s} thigh", f"{s} shank")),
                frozenset((f"{s} shank", f"{s} foot")), frozenset(("thorax", f"{s} upper arm")),
                frozenset((f"{s} upper arm", f"{s} forearm"))} <= edges, edges
    assert {frozenset(("pelvis", "thorax")), frozenset(("thorax", "head"))} <= edges


def test_trunk_trial_grows_to_the_rigid_count_with_the_shoulder_marker_paired():
    """biobuddy's trunk functional trial (Vicon, 59 markers): the eigengap's 11 groups hold
    C2 with the left shoulder marker (18 mm apart) and each foot with its leg. The first
    rigid count, 14, leaves LSHO alone; CLAV is about as rigid with it (5.7 mm) as with its
    own group (4.2 mm), so the pair is the left shoulder girdle and 14 is taken: every
    group rigid, each foot its own segment (the knees do not move in this trial, so thigh
    and shank stay one)."""
    trial, _ = jaxskel.clean.clean(jaxskel.load(DATA / BIOBUDDY / "Test_func_trunk.c3d"))
    seg = jaxskel.segment.segment_markers(trial)
    assert (seg.eigengap_segments, seg.count_rule, seg.n_segments) == (11, "rigid", 14)
    assert seg.nonrigid_groups() == [] and all(len(g) >= 2 for g in seg.groups)
    group_of = {name: g for g in seg.groups for name in g}
    assert group_of["LSHO"] == ("CLAV", "LSHO")
    for side in "LR":
        assert group_of[f"{side}TOE"] != group_of[f"{side}TIB"] == group_of[f"{side}THI"]


def test_cmu_legs_with_automatic_segment_count():
    """CMU subject 02, 15 s, automatic count. The eigengap says 11: the knee markers,
    rigid with thigh and shank alike, chain each thigh's marker into the shank's group
    (A = 12-16 mm, > 4 sigma); the count grows until every group is rigid: 14, with
    both thighs, shanks and feet separate. The legs and pelvis then form the human tree
    (pelvis - thigh - shank - foot on both sides). Q / f topology weight: with the
    paper's raw Q the left thigh was jointed to the right shoulder. Both arms hang off
    the thorax (upper arm, then forearm; the right upper arm was on the head before the
    consistency start of four-marker pairs), and so does the head: the joint costs put
    it on the left upper arm, whose shoulder sweeps 5 degrees in this take (7.06 against
    8.72 mm^2 to the thorax, whose markers bend with the spine), and the pose check
    (``jaxskel.joints._pose_check``) moves it to the thorax, where a centre fixed in both
    segments fits (35 against 898 mm^2). Every joint of the tree is anatomical.
    Against the .asf (printed): left thigh +0 mm, right shank +8 mm, left shank
    -30 mm, right thigh +74 mm. With the paper's per-frame joint centres the hips sat in
    the plane of the four waist markers and both thighs were 8-9 cm long; asserted: the
    left thigh and one shank within 2 cm, every bone within 2 cm or within the bound the
    fit reports for it (right thigh >= 157 mm, left shank >= 492 mm), and the right hip
    named undetermined."""
    result = _fit("nimblephysics/cmu_02_05.c3d", None)
    seg = result.segmentation
    assert (seg.eigengap_segments, seg.count_rule, seg.n_segments) == (11, "rigid", 14)
    assert seg.nonrigid_groups() == []
    assert "grown from the eigengap's 11 until every group is rigid" in result.summary()
    parts = segment_parts(result.trial.labels, result.segmentation.marker_segment)
    legs = {"pelvis"} | {f"{s} {limb}" for s in "LR" for limb in ("thigh", "shank", "foot")}
    assert legs <= set(parts)
    leg_edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist() if {parts[a], parts[b]} & legs}
    expected = {frozenset(p) for s in "LR" for p in (
        ("pelvis", f"{s} thigh"), (f"{s} thigh", f"{s} shank"), (f"{s} shank", f"{s} foot"))}
    assert expected <= leg_edges
    bad = implausible_edges(result.trial.labels, result.segmentation.marker_segment, result.edges)
    assert not [pair for pair in bad if set(pair) & legs], bad
    edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist()}
    arms = {frozenset(p) for s in "LR" for p in (("thorax", f"{s} upper arm"), (f"{s} upper arm", f"{s} forearm"))}
    assert arms <= edges, edges
    assert frozenset(("thorax", "head")) in edges and bad == [], bad
    (exchange,) = [e for e in result.topology.pose_exchanges if e.test == "fixed"]
    assert {parts[s] for s in exchange.removed} == {"L upper arm", "head"}
    assert {parts[s] for s in exchange.added} == {"thorax", "head"}
    assert exchange.misfit[1] < 0.1 * exchange.misfit[0] and exchange.cost[1] > exchange.cost[0]
    text = result.summary()
    exchanges = len(result.topology.pose_exchanges)
    assert f"then {exchanges} joint(s) exchanged by the pose check (below)" in text
    assert text.count("\n  pose check: ") == exchanges
    # the joint costs' choice, rejected by the poses, is not reported as a rival either
    assert not [t for t in result.near_ties() if frozenset(t.rival) == frozenset(exchange.removed)]
    # without the check: the joint costs' tree (the paper's), misfits still reported
    plain = jaxskel.joints.fit_topology(result.trial, result.segmentation, result.topology.pair_costs, pose_check=False)
    assert plain.pose_exchanges == () and frozenset(exchange.removed) in {frozenset(e) for e in plain.edges.tolist()}
    np.testing.assert_array_equal(plain.fixed_misfit, result.topology.fixed_misfit)
    bones = _compare(result, DATA / "timegan_cmu" / "02.asf")
    assert {"L shank", "R shank", "L thigh", "R thigh"} <= set(bones)
    error = {part: abs(fit - ref) for part, (fit, ref, _) in bones.items()}
    assert error["L thigh"] < 0.02
    assert min(error["L shank"], error["R shank"]) < 0.02
    _within_target_or_bound(bones)
    # The right hip (an 11 degree sweep in this take, resolution 167 mm) is named: its
    # thigh (+74 mm) is the bone the recording cannot fix
    right_hip = [j for j, (p, c) in enumerate(result.edges.tolist()) if {parts[p], parts[c]} == {"pelvis", "R thigh"}]
    assert right_hip and right_hip[0] in {u.joint for u in result.undetermined_joints()}


@pytest.mark.extended  # about a minute on 2 cores; CI runs the rest
def test_standing_trial_names_its_joints_unexercised_and_keeps_them():
    """Hamner's static trial (subject standing, 2.5 s): every marker pair keeps its
    distance (largest std 4.3 mm, under the 9 mm rigidity limit), so the automatic count is
    one rigid body and the fit says the recording exercises no joint (before, the eigengap
    cut it in two and the fit returned one joint that turns 0.1 degrees, with a warning).
    Given a count, whatever the segments, their joints barely turn, so the fit warns,
    reports the sweep, and does not move the centres (the anchored refit moved one 1023 mm
    before it checked the sweep)."""
    trial = jaxskel.load(DATA / "opensim_models" / "Hamner" / "subject02_static.trc")
    with pytest.raises(jaxskel.DegenerateMotionError, match="49 markers move as one rigid body"):
        jaxskel.fit_skeleton(trial, ik=False)
    with pytest.warns(jaxskel.DegenerateMotionWarning, match="barely move"):
        result = jaxskel.fit_skeleton(trial, n_segments=2, ik=False)
    report = result.skeleton.diagnostics["anchored"]
    assert len(result.edges) >= 1 and np.all(report["exercise"] < 1.0), report["exercise"]
    assert not report["moved"].any()
    assert "not exercised" in result.summary()


@pytest.mark.extended  # about 1 min; the CI run keeps the other real-data trees (python -m pytest -m extended)
def test_numediart_rolling_take_keeps_its_segments_rigid():
    """numediart 03_rolling: 68 markers, 19 s of rolling on the floor, two labels seen only
    in the first 3.4 s. In that stretch they are falsely rigid with markers all over the
    body, and the spectral step put the left acromion marker (LLAC) in the left thigh's
    group; the left leg then hung off the right hand (bones of 1.19 and 1.56 m). The mend
    of the clustering moves LLAC to the trunk, and the rigid stage places the right
    thigh, two of whose markers are never seen with all the others (that raised
    DegenerateMotionError). Asserted: LLAC with no thigh marker, both thighs jointed to
    the pelvis, every bone shorter than 0.6 m (measured: 104-424 mm); and, judged by the
    set's body-part map (``tests/human_markers.py``), every tree edge anatomical and no
    marker grouped with a body part it is not on (measured: 14 segments, none of either)."""
    result = _fit("numediart/03_rolling.c3d", None)
    seg_of = result.segmentation
    assert implausible_edges(result.trial.labels, seg_of.marker_segment, result.edges) == []
    assert misplaced_markers(result.trial.labels, seg_of.marker_segment, seg_of.distance_std, seg_of.rigid_limit) == []
    labels = np.array(result.trial.labels)
    seg = result.segmentation.marker_segment
    group = {name: int(seg[labels == name][0]) for name in ("LLAC", "LL_TH1", "LR_TH1", "LL_IPS", "LR_IPS")}
    assert not any("_TH" in name for name in labels[seg == group["LLAC"]])
    assert group["LL_IPS"] == group["LR_IPS"]
    edges = {frozenset(map(int, e)) for e in result.edges}
    for thigh in ("LL_TH1", "LR_TH1"):
        assert frozenset((group[thigh], group["LL_IPS"])) in edges
    assert np.max(result.skeleton.bone_lengths) < 0.6, result.skeleton.bone_lengths


#: biobuddy's lower-limb calibration set: marker clusters that sit on one segment each
#: (the markers on joints -- knees, malleoli -- are left out of the check).
BIOBUDDY = Path("biobuddy") / "lower_limb_calibration"
BIOBUDDY_PARTS = {
    "pelvis": ("LASI", "RASI", "LPSI", "RPSI"),
    **{f"{s} thigh": (f"{s}THIB", f"{s}THID", f"{s}THI") for s in "LR"},
    **{f"{s} shank": (f"{s}TIBF", f"{s}TIBD", f"{s}TIB") for s in "LR"},
    **{f"{s} foot": (f"{s}NAV", f"{s}TOE5", f"{s}HEE", f"{s}TOE") for s in "LR"},
}


def _part_segments(result) -> dict[str, int]:
    """Body part -> its segment; asserts each part's markers are in one segment of their own."""
    labels = list(result.trial.labels)
    seg = result.segmentation.marker_segment
    out = {}
    for part, names in BIOBUDDY_PARTS.items():
        segments = {int(seg[labels.index(name)]) for name in names}
        assert len(segments) == 1, (part, segments)
        out[part] = segments.pop()
    assert len(set(out.values())) == len(out), out
    return out


@pytest.mark.extended  # about 1 min; the CI run keeps the other real-data trees (python -m pytest -m extended)
def test_biobuddy_hip_and_knee_trials_fitted_together_give_the_leg_skeleton():
    """biobuddy lower-limb calibration (Vicon, 12 Hz, 60 markers): a functional trial per
    joint. The left-hip trial alone moves no knee, so thigh and shank (and the whole right
    leg) come out as one segment; the two hip and two knee trials fitted together (the
    paper's multi-trial fit) separate pelvis, thighs, shanks and feet and joint them
    anatomically. No ground truth: the two thighs (hip-knee) agree within 2 cm (measured
    441 / 434 mm). With the two ankle trials added the costs joint the left thigh to the
    right thigh and the pose check takes it back (docs/limits.md)."""
    alone = jaxskel.fit_skeleton(jaxskel.load(DATA / BIOBUDDY / "Test_func_lhip.c3d"), ik=False, rigid=False)
    labels, seg = list(alone.trial.labels), alone.segmentation.marker_segment
    assert seg[labels.index("LTHI")] == seg[labels.index("LTIB")]
    assert seg[labels.index("RTHI")] == seg[labels.index("RTIB")]

    trials = [jaxskel.load(DATA / BIOBUDDY / f"Test_func_{name}.c3d") for name in ("lhip", "rhip", "lknee", "rknee")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trials, ik=False)
    assert result.trial_bounds == ((0, 489), (489, 1014), (1014, 1230), (1230, 1447))
    part = _part_segments(result)
    edges = {frozenset(map(int, e)) for e in result.edges}
    for s in "LR":
        for a, b in (("pelvis", f"{s} thigh"), (f"{s} thigh", f"{s} shank"), (f"{s} shank", f"{s} foot")):
            assert frozenset((part[a], part[b])) in edges, (a, b)
    skeleton = result.skeleton
    thigh = {}
    for (j0, j1), length, s in zip(skeleton.bones, skeleton.bone_lengths, skeleton.bone_segment):
        for side in "LR":
            ends = {frozenset(map(int, skeleton.edges[j])) for j in (j0, j1)}
            if s == part[f"{side} thigh"] and ends == {
                frozenset((part["pelvis"], part[f"{side} thigh"])),
                frozenset((part[f"{side} thigh"], part[f"{side} shank"])),
            }:
                thigh[side] = float(length)
    print(f"\nbiobuddy thighs (hip-knee): L {thigh['L'] * 1e3:.0f} mm, R {thigh['R'] * 1e3:.0f} mm")
    assert 0.3 < thigh["L"] < 0.55 and abs(thigh["L"] - thigh["R"]) < 0.02, thigh


@pytest.mark.extended  # about 2 min on 2 cores; the bundled sample's tree runs by default (tests/anatomy/test_identify.py)
def test_cmu_01_01_tree_is_anatomical_with_default_settings():
    """CMU subject 01 (the 41-marker set, forward jumps), default settings. The left upper
    arm carries two markers (LUPA, LELB) and has no pose of its own, so the fixed-centre
    check could not judge it; the joint costs made it a hub, jointed to the right upper arm
    and the head (13.4 and 14.2 against 14.6 mm^2 to the thorax). Its markers about a centre
    fixed in the thorax keep their distances (17 mm^2), about one in the right upper arm or
    the head they do not (72 and 89 mm^2): the sphere check moves both joints."""
    result = _fit("c3d_to_xyz_cmu/01_01.c3d", None)
    labels, seg = result.trial.labels, result.segmentation.marker_segment
    assert implausible_edges(labels, seg, result.edges) == []
    assert misplaced_markers(labels, seg, result.segmentation.distance_std, result.segmentation.rigid_limit) == []
    sphere = [e for e in result.topology.pose_exchanges if e.test == "sphere"]
    assert len(sphere) >= 2 and all(e.misfit[1] * 2 < e.misfit[0] for e in sphere)


@pytest.mark.extended  # about a minute on 2 cores; the pass itself is tested on known answers in tests/joints
def test_pronetorun01_legs_by_the_near_tie_pass():
    """Clouthier's cluster set, prone to running, default settings. Running turns both thighs
    about nearly one axis, so a joint between the thighs costs 7 % less than the right hip
    (8.3 against 8.9 mm^2, within the costs' sampling noise), and the minimum spanning tree
    took it. A centre fixed in the pelvis and the right thigh fits 1.97x better, by more than
    two standard errors of the per-frame differences: the near-tie pass joints the right
    thigh to the pelvis. Every leg joint is anatomical; a joint still wrong is named a near
    tie (head-R upper arm against thorax-R upper arm: misfits 1.34x apart, 1.3 standard
    errors, which the pass does not take)."""
    result = _fit("auto_marker_label/PronetoRun01.c3d", None)
    labels, seg = result.trial.labels, result.segmentation.marker_segment
    parts = segment_parts(labels, seg)
    edges = {frozenset((parts[a], parts[b])) for a, b in result.edges.tolist()}
    legs = {frozenset(p) for s in "LR" for p in (
        ("pelvis", f"{s} thigh"), (f"{s} thigh", f"{s} shank"), (f"{s} shank", f"{s} foot"))}
    assert legs <= edges, edges
    (tie,) = [e for e in result.topology.pose_exchanges if e.test == "near_tie"]
    assert {parts[s] for s in tie.removed} == {"L thigh", "R thigh"}
    assert {parts[s] for s in tie.added} == {"pelvis", "R thigh"}
    assert tie.misfit[1] < tie.misfit[0] / 1.5 and tie.cost[0] < tie.cost[1] < 1.2 * tie.cost[0]
    bad = implausible_edges(labels, seg, result.edges)
    assert len(bad) <= 1 and not [pair for pair in bad if {"thigh", "shank", "foot"} & set(" ".join(pair).split())]
    named = {frozenset((parts[a], parts[b])) for t in result.near_ties() for a, b in (t.edge,)}
    assert {frozenset(pair) for pair in bad} <= named, (bad, named)


@pytest.mark.extended  # about a minute on 2 cores; the mechanism is tested on a synthetic body in tests/skeleton
def test_a_marker_never_seen_with_its_segment_is_left_out_of_a_default_fit(tmp_path):
    """The second half of kineticstoolkit's wheelchair sprint: its ``Sync`` light is clustered
    with the left hand marker but is never seen in a frame with it or with the hand's joint.
    The default fit raised DegenerateMotionError from the rigid stage ("check
    joint_positions"); it now leaves the light out of the skeleton, says so, and finishes
    with the hand and its motion."""
    trial = jaxskel.load(DATA / "kineticstoolkit" / "kinematics_basket_sprint.c3d")
    trial = trial.select_frames(slice(trial.n_frames // 2, trial.n_frames))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(trial)
    said = [str(w.message) for w in caught if issubclass(w.category, jaxskel.DegenerateMotionWarning)]
    assert any("Sync" in text and "never seen in a frame together" in text for text in said), said
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]
    labels = list(result.skeleton.marker_labels)
    assert result.skeleton.diagnostics["unplaced_markers"] == ("Sync",)
    assert result.skeleton.marker_segment[labels.index("Sync")] == -1
    assert result.skeleton.marker_segment[labels.index("HandL")] >= 0
    assert result.motion is not None and np.isfinite(result.motion.joint_positions).all()
    assert "left out of the skeleton: Sync" in result.summary()
    result.save(tmp_path / "sprint.h5")
    saved = jaxskel.load_skeleton(tmp_path / "sprint.h5")
    assert list(saved.diagnostics["unplaced_markers"]) == ["Sync"]
    np.testing.assert_array_equal(saved.marker_segment, result.skeleton.marker_segment)


def test_a_take_the_rigid_skeleton_cannot_hold_keeps_its_joints_and_says_why(tmp_path, capsys):
    """The last third of numediart's 03_rolling (769 frames, rolling on the floor): the trunk is seen
    in 41 frames, never with the left upper arm's other markers, so that arm's joint with the trunk
    cannot be placed on the arm and the rigid fit cannot be built. That stopped the default fit with
    DegenerateMotionError ("check joint_positions"). The fit now keeps its segments, tree and joint
    centres, warns why it has no skeleton (naming the segments and their markers), and the command
    line writes the result before refusing the outputs that need the skeleton."""
    from jaxskel.cli import main

    trial = jaxskel.load(DATA / "numediart" / "03_rolling.c3d")
    third = trial.select_frames(slice(2 * trial.n_frames // 3, trial.n_frames))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jaxskel.fit_skeleton(third)
    said = [w for w in caught if issubclass(w.category, jaxskel.DegenerateMotionWarning)
            and "rigid skeleton could not be fitted" in str(w.message)]
    assert len(said) == 1 and said[0].filename == __file__, [(w.filename, w.lineno) for w in said]
    assert "LLUA1" in str(said[0].message) and "no frame shows enough of these points" in str(said[0].message)
    assert result.skeleton is None and result.motion is None
    assert len(result.edges) == result.n_segments - 1
    assert np.isfinite(result.joint_positions).any(axis=(0, 2)).all()  # every joint placed in some frame
    assert "segments" in result.summary()
    result.save(tmp_path / "third.h5")
    source = jaxskel.save_trial(third, tmp_path / "third.h5.c3d")
    out, bvh = tmp_path / "cli.h5", tmp_path / "cli.bvh"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(["fit", str(source), "-o", str(out), "--bvh", str(bvh), "--quiet"])
    assert code == 2 and "--bvh could not be written" in capsys.readouterr().err
    assert out.is_file() and not bvh.exists()


@pytest.mark.extended  # about 40 s on 2 cores; the scatter's split is tested on synthetic trees by default
def test_a_trunk_clustered_with_the_pelvis_is_split_by_its_scatter():
    """The second half of pyCGM's Movement_trial (1.6 s of walking, Plug-in-Gait): the
    automatic count (11) holds the thorax markers, the pelvis markers and RSHO in one group,
    whose distances vary under the rigidity limit over so short a take. Posed as one rigid
    body, that group's markers scatter by several times the median, so the count grows: the
    pelvis alone, the thorax with its shoulder and back markers, and the tree's pelvis-thorax
    and thorax-head joints (before: pelvis-head, and both arms on the pelvis)."""
    trial = jaxskel.load(DATA / "pycgm" / "Movement_trial.c3d")
    trial = trial.select_frames(slice(trial.n_frames // 2, trial.n_frames))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(trial, ik=False)
    seg = result.segmentation
    assert (seg.count_rule, seg.split_from) == ("split", 11) and result.n_segments > 11
    labels = [lab.split(":")[-1] for lab in result.trial.labels]
    group = {lab: int(s) for lab, s in zip(labels, seg.marker_segment)}
    pelvis = {lab for lab in labels if group[lab] == group["LASI"]}
    assert pelvis == {"LASI", "RASI", "LPSI", "RPSI"} | {lab for lab in pelvis if lab.startswith("*")}
    assert {group[lab] for lab in ("T10", "CLAV", "STRN", "LSHO", "RSHO")} == {group["T10"]} != {group["LASI"]}
    parts = segment_parts(result.trial.labels, seg.marker_segment)
    joints = {frozenset((parts[a], parts[b])) for a, b in np.asarray(result.edges).tolist()}
    assert {frozenset(("pelvis", "thorax")), frozenset(("thorax", "head"))} <= joints
    assert frozenset(("pelvis", "head")) not in joints
