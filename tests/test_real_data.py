"""Every real marker recording in shared/data/real loads with the right units, axes and labels.

Expected values come from shared/data/real/README.md (marker and frame counts,
rates, units, vertical axes, missing fractions, the asf-checked knee-to-ankle
distances). Each file is loaded once per module.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from jaxskel import InputError, UnitsWarning, load, save_trial

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real recordings not found at {DATA}")

# file: (markers after loading with the defaults, frames, Hz, vertical axis, missing %)
# "markers" follows the README; pycgm keeps its 39 markers and 42 unlabelled "*"
# trajectories and drops the Plug-in-Gait outputs (see test_pycgm_drops_model_outputs).
EXPECTED = {
    "biobuddy/functional_trials/right_hip.c3d": (73, 1690, 100, "z", 0.0),
    "biobuddy/functional_trials/right_knee.c3d": (73, 922, 100, "z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_anat.c3d": (59, 131, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/anatomical_posture.c3d": (60, 122, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_lhip.c3d": (60, 489, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_rhip.c3d": (60, 525, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_lknee.c3d": (60, 216, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_rknee.c3d": (60, 217, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_lankle.c3d": (60, 491, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_rankle.c3d": (60, 486, 12, "-z", 0.0),
    "biobuddy/lower_limb_calibration/Test_func_trunk.c3d": (59, 1047, 12, "-z", 1.8),
    "kineticstoolkit/kinematics_tennis_serve.c3d": (39, 1092, 50, "z", 0.0),
    "kineticstoolkit/kinematics_racing_propulsion.c3d": (41, 700, 69.99, "y", 22.2),
    "kineticstoolkit/kinematics_basket_sprint.c3d": (26, 3678, 120, "z", 38.8),
    "numediart/03_rolling.c3d": (68, 2305, 175, "z", 22.9),
    "numediart/85_12.c3d": (41, 4499, 120, "z", 0.0),
    "numediart/HDM_bd_05-01_01_120.c3d": (44, 5920, 120, "z", 0.0),
    "dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d": (44, 202, 120, "z", 0.0),
    "nimblephysics/cmu_02_05.c3d": (41, 1854, 120, "z", 0.0),
    "nimblephysics/squat.c3d": (53, 2539, 120, "y", 1.7),
    "c3d_to_xyz_cmu/01_01.c3d": (42, 2751, 120, "z", 2.4),
    "opensim_models/Hamner/subject02_running.trc": (41, 600, 60, "y", 2.4),
    "opensim_models/Hamner/subject02_static.trc": (49, 300, 60, "y", 0.0),
    "auto_marker_label/S01_Pronetokneel01_mksrem.c3d": (76, 2176, 240, "z", 20.7),
    "auto_marker_label/KneeltoProne01.c3d": (62, 1745, 240, "z", 0.1),
    "auto_marker_label/PronetoRun01.c3d": (62, 1253, 240, "z", 2.5),
    "fjc/RightCross1.csv": (14, 3812, 200, "y", 0.0),
    "fjc/LeftBigCircle1.csv": (14, 3102, 200, "y", 0.0),
    "pycgm/Movement_trial.c3d": (81, 323, 120, "z", 4.0),
}
UNITS_NOT_STATED = {name for name in EXPECTED if name.startswith("auto_marker_label/")}


@pytest.fixture(scope="module")
def loaded():
    """name -> (Trial, warnings raised while loading it)."""
    out = {}
    for name in EXPECTED:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            trial = load(DATA / name)
        out[name] = (trial, [w for w in caught if issubclass(w.category, UnitsWarning)])
    return out


def test_every_marker_recording_is_listed():
    found = {
        p.relative_to(DATA).as_posix()
        for p in DATA.rglob("*")
        if p.suffix.lower() in (".c3d", ".trc", ".csv")
    }
    assert found == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_shape_rate_axis_and_missing(loaded, name):
    trial, _ = loaded[name]
    markers, frames, rate, up, missing_pct = EXPECTED[name]
    assert (trial.n_markers, trial.n_frames) == (markers, frames)
    assert trial.rate == pytest.approx(rate, abs=0.01)
    assert trial.up_axis == up
    assert 100 * (1 - trial.mask.mean()) == pytest.approx(missing_pct, abs=0.06)
    assert trial.source == str(DATA / name)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_positions_are_metres(loaded, name):
    """Inter-marker distances of a human body: median 5 cm - 1.5 m, nothing beyond 15 m."""
    trial, _ = loaded[name]
    x = trial.positions[:: max(1, trial.n_frames // 50)]  # 50 frames are plenty
    d = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1)
    upper_i, upper_j = np.triu_indices(trial.n_markers, 1)
    pairs = d[:, upper_i, upper_j]
    assert 0.05 < np.nanmedian(pairs) < 1.5
    assert np.nanmax(pairs) < 15.0
    # Heights along the vertical lie between the floor and 2.6 m.
    axis = "xyz".index(trial.up_axis[-1])
    sign = -1.0 if trial.up_axis.startswith("-") else 1.0
    heights = sign * trial.positions[..., axis]
    assert np.nanpercentile(heights, 1) > -0.2 and np.nanpercentile(heights, 99) < 2.6


@pytest.mark.parametrize(
    "name, pair, metres",
    [
        ("dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d", ("LKNE", "LANK"), 0.441),
        ("numediart/HDM_bd_05-01_01_120.c3d", ("LKNE", "LANK"), 0.392),
        ("nimblephysics/cmu_02_05.c3d", ("LKNE", "LANK"), 0.408),
    ],
)
def test_knee_to_ankle_distance_matches_asf_tibia(loaded, name, pair, metres):
    trial, _ = loaded[name]
    i, j = trial.marker_index(pair)
    dist = np.linalg.norm(trial.positions[:, i] - trial.positions[:, j], axis=-1)
    assert np.nanmedian(dist) == pytest.approx(metres, abs=0.002)


def test_units_warning_only_where_units_are_not_stated(loaded):
    for name, (trial, units_warnings) in loaded.items():
        if name in UNITS_NOT_STATED:
            assert len(units_warnings) == 1, name
            assert trial.metadata["units_source"] == "assumed"
            assert trial.metadata["original_units"] == "mm"
        else:
            assert units_warnings == [], name
            assert trial.metadata["units_source"] == "file"
    assert (
        loaded["kineticstoolkit/kinematics_tennis_serve.c3d"][0].metadata["original_units"] == "m"
    )


def test_subject_prefixes_are_stripped(loaded):
    tennis = loaded["kineticstoolkit/kinematics_tennis_serve.c3d"][0]
    assert tennis.metadata["label_prefixes"] == ["Derrick"]
    assert {"LANK", "RANK", "C7", "T10"} <= set(tennis.labels)
    assert not any(":" in lab for lab in tennis.labels)
    squat = loaded["nimblephysics/squat.c3d"][0]
    assert squat.metadata["label_prefixes"] == ["SehoonVSK35"] and "LIEL" in squat.labels


def test_optitrack_rigid_body_labels_stay_distinct(loaded):
    """'ArmL:Marker1' and 'SWL:Marker1' would both become 'Marker1': they keep their prefix."""
    sprint = loaded["kineticstoolkit/kinematics_basket_sprint.c3d"][0]
    assert {"ArmL:Marker1", "SWL:Marker1", "WheelchairL:Marker1", "ForearmL:Marker4"} <= set(
        sprint.labels
    )
    assert {"Forehead", "HandL", "Sync"} <= set(sprint.labels)  # unique names are stripped
    assert len(sprint.metadata["kept_prefix_labels"]) == 16


def test_pycgm_drops_model_outputs(loaded):
    """Plug-in-Gait angles/forces/moments/powers and its segment points are not markers.

    The 76 segment points (LFEO/LFEA/LFEL/LFEP = left femur origin = knee centre,
    ... PELP, HEDO) are joint-centre estimates: useful as reference, so
    ``drop_non_markers=False`` keeps them, but not markers, so the default drops
    them with the 82 non-position outputs. 39 markers and the 42 unlabelled
    trajectories remain.
    """
    trial = loaded["pycgm/Movement_trial.c3d"][0]
    unlabeled = [lab for lab in trial.labels if lab.startswith("*")]
    assert len(unlabeled) == 42 and len(trial.labels) - len(unlabeled) == 39
    assert {"LASI", "RASI", "LKNE", "LANK", "LHEE", "C7"} <= set(trial.labels)
    assert trial.metadata["n_dropped"] == 76 + 82
    reasons = trial.metadata["dropped_reasons"]
    assert reasons["LFEP"] == "Plug-in-Gait segment point"
    assert reasons["LHipAngles"] == "angles" and reasons["CentreOfMass"] == "modeled_markers"

    everything = load(
        DATA / "pycgm/Movement_trial.c3d", drop_non_markers=False, drop_unlabeled=True
    )
    assert everything.n_markers == 39 + 76 + 2
    assert "LFEP" in everything.labels and "LHipAngles" not in everything.labels
    # LFEO (knee centre) lies within a few cm of the lateral knee marker.
    i, j = everything.marker_index(["LFEO", "LKNE"])
    knee_gap = np.nanmedian(
        np.linalg.norm(everything.positions[:, i] - everything.positions[:, j], axis=-1)
    )
    assert 0.02 < knee_gap < 0.12


def test_unlabelled_slots(loaded):
    raw = loaded["auto_marker_label/S01_Pronetokneel01_mksrem.c3d"][0]
    assert raw.labels == tuple(f"*{i}" for i in range(76))
    with pytest.raises(InputError, match="all 76 points were dropped"):
        load(
            DATA / "auto_marker_label/S01_Pronetokneel01_mksrem.c3d",
            drop_unlabeled=True,
            units="mm",
        )
    hdm = load(DATA / "numediart/HDM_bd_05-01_01_120.c3d", drop_unlabeled=True)
    assert hdm.n_markers == 41 and hdm.metadata["dropped_labels"] == ["*0", "*1", "*2"]


def test_never_seen_markers_are_kept_as_missing(loaded):
    running = loaded["opensim_models/Hamner/subject02_running.trc"][0]
    assert not running.mask[:, running.marker_index("L.Bicep")].any()  # all zeros in the file
    racing = loaded["kineticstoolkit/kinematics_racing_propulsion.c3d"][0]
    probes = racing.marker_index([f"Probe{i}" for i in range(1, 7)])
    assert not racing.mask[:, probes].any()
    trunk = loaded["biobuddy/lower_limb_calibration/Test_func_trunk.c3d"][0]
    assert not trunk.mask[:, trunk.marker_index("*58")].any()


def test_up_axis_sources(loaded):
    """Files stating Y_SCREEN supply the axis letter; the data supply the sign."""
    for name, (trial, _) in loaded.items():
        expected = "file+data" if trial.metadata.get("stated_up_axis") else "data"
        assert trial.metadata["up_axis_source"] == expected, name
    # biobuddy's rotated files still say +Z and Qualisys writes -Z for Z-up data.
    anat = loaded["biobuddy/lower_limb_calibration/Test_func_anat.c3d"][0]
    assert anat.metadata["stated_up_axis"] == "+Z" and anat.up_axis == "-z"
    hip = loaded["biobuddy/functional_trials/right_hip.c3d"][0]
    assert hip.metadata["stated_up_axis"] == "-Z" and hip.up_axis == "z"


def test_truncated_copy_of_a_real_file(tmp_path):
    data = (DATA / "dynamic_clustering_hdm05/HDM_dg_06-03_03_120.c3d").read_bytes()
    cut = tmp_path / "HDM_dg_cut.c3d"
    cut.write_bytes(data[: len(data) - 1000])
    with pytest.raises(InputError, match="HDM_dg_cut.c3d.*truncated"):
        load(cut)


@pytest.mark.parametrize("suffix", [".h5", ".c3d", ".trc"])
def test_real_trial_round_trip(loaded, tmp_path, suffix):
    trial = loaded["numediart/03_rolling.c3d"][0]
    back = load(save_trial(trial, tmp_path / f"rolling{suffix}"))
    assert back.labels == trial.labels and back.up_axis == trial.up_axis
    assert back.rate == trial.rate and back.metadata["first_frame"] == trial.metadata["first_frame"]
    np.testing.assert_array_equal(back.mask, trial.mask)
    np.testing.assert_allclose(back.positions, trial.positions, atol=1e-6)
