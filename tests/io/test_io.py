"""File I/O: readers, writers, conventions and failure modes, on files made here.

Every C3D is written with ezc3d directly (not with jaxskel's writer) unless the
test is a round trip, so the reader is checked against an independent writer.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import ezc3d
import h5py
import numpy as np
import pytest

from jaxskel import InputError, SchemaError, Trial, UnitsWarning, load, save_trial
from jaxskel.io import infer_up_axis, rotation_between_axes
from jaxskel.io._atomic import atomic_output

# ----------------------------------------------------------------- helpers


def write_c3d_file(path, points, labels, *, rate=100.0, units="mm", params=None):
    """A C3D written by ezc3d itself: points (F, M, 3) in file units, NaN = not seen."""
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    data = np.ones((4, points.shape[1], points.shape[0]))
    data[:3] = np.transpose(points, (2, 1, 0))
    c3d["data"]["points"] = data
    if units is not None:
        c3d.add_parameter("POINT", "UNITS", [units])
    for (group, name), value in (params or {}).items():
        c3d.add_parameter(group, name, value)
    c3d.write(str(path))
    return Path(path)


def standing_body(n_frames=120, up="z", seed=0, origin=(0.0, 0.0)):
    """Markers of an upright person walking forward (metres), in a lab with ``up`` vertical.

    Built Z-up (x forward, y left): two feet of three markers on the floor,
    knees, pelvis, shoulders, head; then rotated so that +z becomes ``up``.
    """
    rng = np.random.default_rng(seed)
    body = np.array(
        [
            [-0.10, 0.10, 0.05],
            [0.12, 0.10, 0.03],
            [-0.05, 0.12, 0.09],  # left heel, toe, ankle
            [-0.10, -0.10, 0.05],
            [0.12, -0.10, 0.03],
            [-0.05, -0.12, 0.09],  # right foot
            [0.02, 0.10, 0.50],
            [0.02, -0.10, 0.50],  # knees
            [0.10, 0.12, 1.00],
            [0.10, -0.12, 1.00],
            [-0.10, 0.0, 1.05],  # pelvis
            [0.0, 0.18, 1.45],
            [0.0, -0.18, 1.45],
            [0.05, 0.0, 1.40],  # shoulders, sternum
            [0.08, 0.0, 1.70],
            [-0.08, 0.0, 1.72],  # head
        ]
    )
    t = np.arange(n_frames) / 60.0
    walk = np.stack([origin[0] + 1.2 * t, origin[1] + 0.05 * np.sin(2 * t), 0 * t], axis=1)
    x = body[None] + walk[:, None] + rng.normal(0, 0.005, (n_frames, len(body), 3))
    x[..., 2] = np.maximum(x[..., 2], 0.02)
    return x @ rotation_between_axes("z", up).T


def trial_with_gaps(n_frames=40, seed=1):
    x = standing_body(n_frames, seed=seed)
    x[5:9, 2] = np.nan
    x[:, 7] = np.nan  # a marker never seen
    labels = [f"M{i}" for i in range(x.shape[1])]
    return Trial(x, labels, 120.0, up_axis="z", source="test", metadata={"first_frame": 7})


# ----------------------------------------------------------------- atomic output


def test_atomic_output_writes_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "out.txt"
    with atomic_output(target) as tmp:
        assert tmp.parent == tmp_path and tmp != target
        tmp.write_text("done")
        assert not target.exists()  # nothing visible until the body finished
    assert target.read_text() == "done"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_output_refuses_to_overwrite(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(InputError, match="already exists.*overwrite=True"):
        with atomic_output(target) as tmp:
            tmp.write_text("new")
    assert target.read_text() == "old"
    with atomic_output(target, overwrite=True) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_output_refuses_a_name_taken_during_the_write(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(InputError, match="created by someone else"):
        with atomic_output(target) as tmp:
            tmp.write_text("mine")
            target.write_text("theirs")
    assert target.read_text() == "theirs"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_output_failure_keeps_existing_file_and_removes_temporary(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="disk on fire"):
        with atomic_output(target, overwrite=True) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk on fire")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_output_bad_destinations(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        with atomic_output(tmp_path / "missing" / "out.txt") as tmp:
            tmp.write_text("x")
    with pytest.raises(InputError, match="is a directory"):
        with atomic_output(tmp_path) as tmp:
            tmp.write_text("x")
    with pytest.raises(InputError, match="produced no file"):
        with atomic_output(tmp_path / "out.txt"):
            pass
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------- round trips


@pytest.mark.parametrize("suffix, tol", [(".h5", 0.0), (".c3d", 1e-6), (".trc", 1e-9)])
def test_round_trip(tmp_path, suffix, tol):
    trial = trial_with_gaps()
    path = save_trial(trial, tmp_path / f"trial{suffix}")
    back = load(path)
    assert back.labels == trial.labels
    assert back.rate == trial.rate
    assert back.up_axis == "z"
    assert back.metadata["first_frame"] == 7
    np.testing.assert_array_equal(back.mask, trial.mask)
    np.testing.assert_allclose(back.positions, trial.positions, atol=tol, rtol=0)
    assert back.metadata["file"] == str(path)  # where this load read it (jaxskel never writes over it)
    if suffix == ".h5":
        assert dict(back.metadata) == {**trial.metadata, "file": str(path)}
    else:
        assert back.metadata["original_units"] == "mm"
        assert back.metadata["reader"] == suffix[1:]
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"trial{suffix}"]


def test_h5_round_trip_is_exact_including_metadata(tmp_path):
    trial = trial_with_gaps().replace(
        metadata={"first_frame": 3, "reader": "c3d", "dropped_labels": ["*1"], "n": np.int64(4)},
        up_axis="-y",
    )
    trial.save(tmp_path / "t.h5")
    back = load(tmp_path / "t.h5")
    assert back.source == "test"
    assert back.up_axis == "-y"
    assert dict(back.metadata) == {
        "first_frame": 3,
        "reader": "c3d",
        "dropped_labels": ["*1"],
        "n": 4,
        "file": str(tmp_path / "t.h5"),
    }
    back.save(tmp_path / "again.h5")  # "file" is never stored: each load sets its own
    assert load(tmp_path / "again.h5").metadata["file"] == str(tmp_path / "again.h5")
    assert np.array_equal(back.positions, trial.positions, equal_nan=True)


def test_c3d_writer_marks_missing_samples_the_c3d_way(tmp_path):
    """Coordinates (0, 0, 0) and residual -1, read by ezc3d itself as NaN."""
    path = save_trial(trial_with_gaps(), tmp_path / "gaps.c3d")
    c3d = ezc3d.c3d(str(path))
    residuals = c3d["data"]["meta_points"]["residuals"][0]  # (M, F)
    np.testing.assert_array_equal(residuals < 0, ~trial_with_gaps().mask.T)
    assert np.isnan(c3d["data"]["points"][:3, 7]).all()
    assert np.isfinite(c3d["data"]["points"][:3, 0]).all()


def test_c3d_round_trip_keeps_unknown_up_axis_and_many_labels(tmp_path):
    # > 255 points need POINT:LABELS2; a stated "unknown" axis must not be re-inferred.
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 1.5, (6, 300, 3))
    trial = Trial(x, [f"m{i}" for i in range(300)], 240.0, up_axis="unknown")
    back = load(save_trial(trial, tmp_path / "many.c3d"))
    assert back.labels == trial.labels
    assert back.up_axis == "unknown" and back.metadata["up_axis_source"] == "file"
    np.testing.assert_allclose(back.positions, x, atol=1e-6)


def test_save_trial_refuses_overwrite_and_unknown_suffix(tmp_path):
    trial = trial_with_gaps()
    path = save_trial(trial, tmp_path / "t.trc")
    before = path.read_bytes()
    with pytest.raises(InputError, match="already exists"):
        save_trial(trial.replace(rate=50.0), path)
    assert path.read_bytes() == before
    save_trial(trial.replace(rate=50.0), path, overwrite=True)
    assert load(path).rate == 50.0
    with pytest.raises(InputError, match=r"unknown file type '\.bvh'"):
        save_trial(trial, tmp_path / "t.bvh")


def test_failing_write_leaves_existing_file_intact(tmp_path, monkeypatch):
    trial = trial_with_gaps()
    path = save_trial(trial, tmp_path / "t.h5")
    before = path.read_bytes()

    def broken_create_dataset(self, *args, **kwargs):
        raise RuntimeError("simulated failure half-way through the write")

    # Fault injection, the only way to make a write fail half-way through on purpose.
    monkeypatch.setattr(h5py.Group, "create_dataset", broken_create_dataset)
    with pytest.raises(RuntimeError, match="half-way"):
        save_trial(trial.replace(rate=1.0), path, overwrite=True)
    with pytest.raises(RuntimeError, match="half-way"):
        save_trial(trial, tmp_path / "new.h5")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.h5"]


# ----------------------------------------------------------------- C3D reading


@pytest.mark.parametrize("units, per_metre", [("mm", 1000.0), ("cm", 100.0), ("m", 1.0)])
def test_c3d_units_become_metres(tmp_path, units, per_metre):
    x = standing_body(30)
    path = write_c3d_file(
        tmp_path / f"u_{units}.c3d", x * per_metre, [f"M{i}" for i in range(16)], units=units
    )
    trial = load(path)
    np.testing.assert_allclose(trial.positions, x, atol=1e-6)
    assert trial.metadata["original_units"] == units
    assert trial.metadata["units_source"] == "file"


def test_c3d_without_units_warns_and_assumes_mm_unless_values_are_metre_sized(tmp_path):
    x = standing_body(30)
    labels = [f"M{i}" for i in range(16)]
    in_mm = write_c3d_file(tmp_path / "mm.c3d", x * 1000.0, labels, units=None)
    with pytest.warns(UnitsWarning, match="does not state its length unit.*millimetres"):
        trial = load(in_mm)
    np.testing.assert_allclose(trial.positions, x, atol=1e-6)
    assert trial.metadata["units_source"] == "assumed"

    in_m = write_c3d_file(tmp_path / "m.c3d", x, labels, units=None)
    with pytest.warns(UnitsWarning, match="must be metres"):
        trial = load(in_m)
    np.testing.assert_allclose(trial.positions, x, atol=1e-6)

    # An explicit unit overrides the file and silences the warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        trial = load(in_mm, units="cm")
    np.testing.assert_allclose(trial.positions, x * 10.0, atol=1e-5)
    with pytest.raises(InputError, match="unknown length unit 'furlong'"):
        load(in_mm, units="furlong")


def test_c3d_prefixes_duplicates_and_blank_labels(tmp_path):
    x = standing_body(20)[:, :6]
    labels = ["Bob:LKNE", "Bob:RKNE", "ArmL:Marker1", "SWL:Marker1", "Bob:C7", "Bob:C7"]
    trial = load(write_c3d_file(tmp_path / "p.c3d", x * 1000.0, labels))
    # Colliding stripped names keep their prefixes; exact duplicates get a suffix.
    assert trial.labels == ("LKNE", "RKNE", "ArmL:Marker1", "SWL:Marker1", "C7", "C7_2")
    assert trial.metadata["label_prefixes"] == ["ArmL", "Bob", "SWL"]
    assert trial.metadata["kept_prefix_labels"] == ["ArmL:Marker1", "SWL:Marker1"]
    assert trial.metadata["renamed_labels"] == {"Bob:C7 #5": "C7_2"}
    np.testing.assert_allclose(trial.positions, x, atol=1e-6)


def test_c3d_missing_samples_nan_and_exact_zeros(tmp_path):
    x = standing_body(20)[:, :4] * 1000.0
    x[3, 0] = np.nan  # written with residual -1 by ezc3d
    x[4, 1] = 0.0  # Vicon-style "not seen"
    x[5, 2] = [0.0, 0.0, 7.0]  # a real sample that merely has zeros in it
    trial = load(write_c3d_file(tmp_path / "gaps.c3d", x, ["A", "B", "C", "D"]))
    expected = np.ones((20, 4), bool)
    expected[3, 0] = expected[4, 1] = False
    np.testing.assert_array_equal(trial.mask, expected)
    np.testing.assert_allclose(trial.positions[5, 2], [0.0, 0.0, 0.007])


def test_c3d_unlabeled_and_non_marker_points(tmp_path):
    x = standing_body(20)[:, :7] * 1000.0
    labels = ["LKNE", "RKNE", "*0", "*12", "LFEP", "CentreOfMass", "LKneeAngles"]
    params = {
        ("POINT", "ANGLES"): ["LKneeAngles"],
        ("POINT", "MODELED_MARKERS"): ["CentreOfMass"],
    }
    path = write_c3d_file(tmp_path / "pig.c3d", x, labels, params=params)

    default = load(path)
    assert default.labels == ("LKNE", "RKNE", "*0", "*12")
    assert default.metadata["n_dropped"] == 3
    assert default.metadata["dropped_reasons"] == {
        "LFEP": "Plug-in-Gait segment point",
        "CentreOfMass": "modeled_markers",
        "LKneeAngles": "angles",
    }
    assert load(path, drop_unlabeled=True).labels == ("LKNE", "RKNE")
    # Computed positions can be kept; angles are never positions.
    everything = load(path, drop_non_markers=False)
    assert everything.labels == ("LKNE", "RKNE", "*0", "*12", "LFEP", "CentreOfMass")


def test_c3d_with_only_non_markers_or_no_points_is_rejected(tmp_path):
    x = standing_body(10)[:, :2] * 1000.0
    path = write_c3d_file(
        tmp_path / "angles.c3d",
        x,
        ["LHipAngles", "RHipAngles"],
        params={("POINT", "ANGLES"): ["LHipAngles", "RHipAngles"]},
    )
    with pytest.raises(InputError, match="angles.c3d.*all 2 points were dropped"):
        load(path)
    path = write_c3d_file(tmp_path / "raw.c3d", x, ["*0", "*1"])
    with pytest.raises(InputError, match="raw.c3d.*drop_unlabeled=False"):
        load(path, drop_unlabeled=True)

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [100]
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = ("emg",)
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = [100]
    c3d["data"]["analogs"] = np.zeros((1, 1, 10))
    c3d["data"]["points"] = np.zeros((4, 0, 10))
    c3d.write(str(tmp_path / "analog.c3d"))
    with pytest.raises(InputError, match="analog.c3d contains no 3D points"):
        load(tmp_path / "analog.c3d")


def test_c3d_metadata(tmp_path):
    # (ezc3d aborts writing a "Vicon" file without a TRIAL group, hence Qualisys.)
    params = {("MANUFACTURER", "COMPANY"): ["Qualisys"], ("POINT", "Y_SCREEN"): ["+Z"]}
    path = write_c3d_file(
        tmp_path / "m.c3d",
        standing_body(12) * 1000.0,
        [f"M{i}" for i in range(16)],
        rate=150.0,
        params=params,
    )
    meta = load(path).metadata
    assert meta["reader"] == "c3d"
    assert meta["manufacturer"] == "Qualisys"
    assert meta["stated_up_axis"] == "+Z"
    assert meta["first_frame"] == 1
    assert meta["n_dropped"] == 0 and meta["dropped_labels"] == []


# ----------------------------------------------------------------- up axis


@pytest.mark.parametrize("up", ["z", "y", "-z", "-y"])
def test_infer_up_axis_standing_body(up):
    x = standing_body(up=up, origin=(2.5, -1.0))
    axis, scores = infer_up_axis(x)
    assert axis == up
    assert scores[up] - sorted(scores.values())[-2] > 0.5


def test_infer_up_axis_is_invariant_to_marker_order_and_horizontal_position():
    x = standing_body(up="y", origin=(0.3, 0.1))
    axis, scores = infer_up_axis(x)
    perm = np.random.default_rng(3).permutation(x.shape[1])
    moved = x[:, perm] + np.array([-4.0, 0.0, 3.0])  # y is vertical: move in x and z only
    axis2, scores2 = infer_up_axis(moved)
    assert axis2 == axis == "y"
    # Horizontal candidates see the move (the lab origin matters to them), the vertical does not.
    assert scores2["y"] == pytest.approx(scores["y"]) and scores2["-y"] == pytest.approx(
        scores["-y"]
    )


def test_infer_up_axis_lying_body_uses_floor_contact():
    # Prone on the floor along x: the long extent is horizontal, the floor decides.
    rng = np.random.default_rng(0)
    n = 16
    body = np.stack(
        [np.linspace(0.0, 1.7, n), rng.uniform(-0.2, 0.2, n), rng.uniform(0.03, 0.25, n)], axis=1
    )
    x = body[None] + rng.normal(0, 0.003, (50, n, 3))
    assert infer_up_axis(x)[0] == "z"
    assert infer_up_axis(x @ rotation_between_axes("z", "y").T)[0] == "y"


def test_infer_up_axis_lower_body_without_feet_uses_long_axis():
    # Pelvis and thigh markers only (0.45-1.05 m high, nothing on the floor), Y up.
    rng = np.random.default_rng(1)
    heights = np.array([1.0, 1.0, 1.02, 1.02, 0.8, 0.7, 0.6, 0.5, 0.48, 0.8, 0.7, 0.6, 0.5, 0.48])
    side = np.array(
        [0.12, -0.12, 0.1, -0.1, 0.1, 0.11, 0.1, 0.1, 0.05, -0.1, -0.11, -0.1, -0.1, -0.05]
    )
    fwd = rng.uniform(-0.08, 0.08, 14)
    body = np.stack([side, heights, fwd], axis=1)
    x = body[None] + rng.normal(0, 0.01, (60, 14, 3))
    assert infer_up_axis(x)[0] == "y"


def test_infer_up_axis_degenerate_input():
    assert infer_up_axis(np.full((5, 3, 3), np.nan)) == ("unknown", {})
    with pytest.raises(InputError, match="candidate"):
        infer_up_axis(standing_body(5), candidates=("w",))


def test_c3d_screen_letter_is_trusted_but_sign_comes_from_data(tmp_path):
    # Like biobuddy's rotated files: the file says +Z, the body hangs below z = 0.
    x = standing_body(up="-z") * 1000.0
    path = write_c3d_file(
        tmp_path / "rot.c3d",
        x,
        [f"M{i}" for i in range(16)],
        params={("POINT", "Y_SCREEN"): ["+Z"], ("POINT", "X_SCREEN"): ["+X"]},
    )
    trial = load(path)
    assert trial.up_axis == "-z"
    assert trial.metadata["up_axis_source"] == "file+data"
    override = load(path, up_axis="y")
    assert override.up_axis == "y" and override.metadata["up_axis_source"] == "argument"
    with pytest.raises(InputError, match="up_axis must be one of"):
        load(path, up_axis="up")


# ----------------------------------------------------------------- TRC and CSV


def _trc_text(rows, names=("A", "B", "C"), n_frames=None, units="mm"):
    n_frames = len(rows) if n_frames is None else n_frames
    head = [
        "PathFileType\t4\t(X/Y/Z)\tx.trc",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"50.00\t50.00\t{n_frames}\t{len(names)}\t{units}\t50.00\t11\t{n_frames}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, len(names) + 1)) + "\t",
        "",
    ]
    return "\n".join(head + rows) + "\n"


def test_trc_tolerates_trailing_tabs_short_rows_and_unseen_markers(tmp_path):
    rows = [
        "11\t0.00\t1\t2\t3\t\t\t\t100\t200\t300\t",  # B missing, trailing tab
        "12\t0.02\t4\t5\t6\t\t\t\t0\t0\t0\t\t",  # C at (0,0,0): missing
        "13\t0.04\t7\t8\t9",  # row ends early
    ]
    path = tmp_path / "t.trc"
    path.write_text(_trc_text(rows))
    trial = load(path, up_axis="z")
    assert trial.labels == ("A", "B", "C")
    assert trial.rate == 50.0
    assert trial.metadata["first_frame"] == 11
    np.testing.assert_allclose(
        trial.positions[:, 0], [[0.001, 0.002, 0.003], [0.004, 0.005, 0.006], [0.007, 0.008, 0.009]]
    )
    assert np.isnan(trial.positions[:, 1]).all()  # never seen: kept, all missing
    np.testing.assert_array_equal(trial.mask[:, 2], [True, False, False])


def test_trc_writer_header(tmp_path):
    trial = trial_with_gaps().replace(rate=69.99261474609375)
    lines = save_trial(trial, tmp_path / "h.trc").read_text().splitlines()
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    assert header == {
        "DataRate": "69.9926147461",
        "CameraRate": "69.9926147461",
        "NumFrames": "40",
        "NumMarkers": "16",
        "Units": "mm",
        "OrigDataRate": "69.9926147461",
        "OrigDataStartFrame": "7",
        "OrigNumFrames": "40",
    }
    assert lines[3].split("\t")[:5] == ["Frame#", "Time", "M0", "", ""]
    assert lines[6].split("\t")[:2] == ["7", "0.000000"]  # Frame# from first_frame, time from 0
    assert lines[6].split("\t")[2 + 3 * 7 : 5 + 3 * 7] == ["", "", ""]  # never-seen marker


def test_trc_errors_name_the_file(tmp_path):
    good = ["1\t0.00\t1\t2\t3\t4\t5\t6\t7\t8\t9"]
    cases = {
        "short.trc": (_trc_text(good, n_frames=5), "truncated: the header says NumFrames=5"),
        "cut.trc": (_trc_text(good + ["2\t0.02\t1\t2"]).rstrip("\n"), "last row .* is cut off"),
        "names.trc": (
            _trc_text(good, names=("A", "B")).replace("\t2\tmm", "\t3\tmm"),
            "NumMarkers=3",
        ),
        "word.trc": (
            _trc_text(["1\t0.00\t1\t2\tthree\t4\t5\t6\t7\t8\t9"]),
            "line 7, column 5: 'three'",
        ),
        "extra.trc": (_trc_text(["1\t0.00\t1\t2\t3\t4\t5\t6\t7\t8\t9\t10"]), "at most 11"),
        "plain.trc": ("hello\n", "not a TRC file"),
    }
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=message) as err:
            load(tmp_path / name)
        assert name in str(err.value)


def _cortex_csv(rows, n_frames=None):
    n_frames = len(rows) if n_frames is None else n_frames
    return (
        "\n".join(
            [
                f"Frame number,{n_frames}",
                "First frame,3",
                "Point frequency,200",
                "Analog frequency,1000",
                "",
                "Time,Hip,,,Knee,,",
                "s,mm,mm,mm,mm,mm,mm",
                ",X,Y,Z,X,Y,Z",
                *rows,
            ]
        )
        + "\n"
    )


def test_cortex_csv(tmp_path):
    path = tmp_path / "hip.csv"
    path.write_text(_cortex_csv(["0,10,1000,20,15,500,25,", "0.005,11,1001,,16,501,26"]))
    trial = load(path, up_axis="y")
    assert trial.labels == ("Hip", "Knee")
    assert trial.rate == 200.0
    assert trial.metadata["first_frame"] == 3 and trial.metadata["reader"] == "csv"
    np.testing.assert_allclose(trial.positions[0], [[0.010, 1.0, 0.020], [0.015, 0.5, 0.025]])
    assert trial.mask.tolist() == [[True, True], [False, True]]

    (tmp_path / "short.csv").write_text(_cortex_csv(["0,10,1000,20,15,500,25"], n_frames=3))
    with pytest.raises(InputError, match="short.csv.*truncated"):
        load(tmp_path / "short.csv")
    (tmp_path / "other.csv").write_text("a,b,c\n1,2,3\n")
    with pytest.raises(InputError, match="other.csv.*Cortex/MAC3D"):
        load(tmp_path / "other.csv")


# ----------------------------------------------------------------- corrupt files


@pytest.fixture
def real_c3d(tmp_path):
    """A complete C3D (200 frames x 16 markers) written by ezc3d."""
    return write_c3d_file(
        tmp_path / "walk.c3d", standing_body(200) * 1000.0, [f"M{i}" for i in range(16)]
    )


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda b: b[: len(b) - 2000], "truncated: it announces 200 frames"),
        (lambda b: b[: len(b) // 2], "truncated"),
        (lambda b: b[:300], "shorter than a C3D header"),
        (lambda b: b[:1500], "not a valid C3D file|truncated"),
        (lambda b: np.random.default_rng(0).bytes(4096), "not a C3D file"),
        (lambda b: b"", "the file is empty"),
        (lambda b: b"just some text\n" * 100, "not a C3D file"),
    ],
    ids=[
        "truncated-data",
        "half",
        "header-only",
        "truncated-parameters",
        "random",
        "empty",
        "text",
    ],
)
def test_corrupt_c3d_is_an_input_error_naming_the_file(real_c3d, make, message):
    bad = real_c3d.with_name("bad.c3d")
    bad.write_bytes(make(real_c3d.read_bytes()))
    with pytest.raises(InputError, match=message) as err:
        load(bad)
    assert "bad.c3d" in str(err.value)


def _parameter_field(data, name):
    """Byte position of the data type of parameter POINT:``name`` in an ezc3d-written file."""
    at = 0
    while True:
        at = data.index(name.encode(), at + 1)
        # name length (negative when locked), then group id 1 (POINT), then the name
        if data[at - 2] in (len(name), 256 - len(name)) and data[at - 1] == 1:
            return at + len(name) + 2  # skip the name and the next-record offset


@pytest.mark.parametrize(
    "damage, message",
    [
        # POINT:FRAMES as an empty 50x0 array (ezc3d dereferences the missing value)
        (
            lambda d: d.__setitem__(_parameter_field(d, "FRAMES") + 1, 2),
            "POINT:FRAMES holds no number",
        ),
        # POINT:FRAMES says 562 frames but the file holds 50 (ezc3d reads past the end)
        (lambda d: d.__setitem__(_parameter_field(d, "FRAMES") + 3, 2), "announces 562 frames"),
        # POINT:USED claims 171 dimensions, running into the following records
        (
            lambda d: d.__setitem__(_parameter_field(d, "USED") + 1, 171),
            "corrupt C3D parameter record",
        ),
        # POINT:RATE turned into text
        (lambda d: d.__setitem__(_parameter_field(d, "RATE"), 255), "POINT:RATE holds no number"),
    ],
    ids=["empty-frames", "frames-beyond-data", "171-dimensions", "rate-as-text"],
)
def test_damaged_c3d_parameters_are_rejected_before_ezc3d_reads_them(tmp_path, damage, message):
    """Each of these made ezc3d crash the interpreter (segfault) before the layout check."""
    path = write_c3d_file(
        tmp_path / "ok.c3d", standing_body(50) * 1000.0, [f"M{i}" for i in range(16)]
    )
    data = bytearray(path.read_bytes())
    damage(data)
    bad = tmp_path / "damaged.c3d"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=message) as err:
        load(bad)
    assert "damaged.c3d" in str(err.value)


def test_corrupt_and_foreign_h5_files(tmp_path):
    good = save_trial(trial_with_gaps(), tmp_path / "good.h5")
    data = good.read_bytes()
    (tmp_path / "half.h5").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.h5").write_text("not hdf5")
    with h5py.File(tmp_path / "nodata.h5", "w") as h5:
        h5.attrs["jaxskel_trial_version"] = 1
        h5.create_dataset("labels", data=np.array(["a"], dtype=object), dtype=h5py.string_dtype())
    with h5py.File(tmp_path / "plain.h5", "w") as h5:
        h5.create_dataset("positions", data=np.zeros((2, 1, 3)))
    with h5py.File(tmp_path / "result.h5", "w") as h5:
        h5.attrs["schema_version"] = 1
    expected = {
        "half.h5": "cannot read .*half.h5",
        "text.h5": "text.h5: not a valid HDF5 file",
        "nodata.h5": "nodata.h5: jaxskel trial without a 'positions' dataset",
        "plain.h5": "plain.h5 is not a jaxskel trial",
        "result.h5": "result.h5 is a jaxskel result file.*load_result",
    }
    for name, message in expected.items():
        with pytest.raises(InputError, match=message):
            load(tmp_path / name)

    with h5py.File(good, "a") as h5:
        h5.attrs["jaxskel_trial_version"] = 99
    with pytest.raises(SchemaError, match="version 99"):
        load(good)
    with pytest.raises(InputError, match="units= does not apply"):
        load(save_trial(trial_with_gaps(), tmp_path / "again.h5"), units="mm")


def test_missing_file_unknown_suffix_and_directory(tmp_path):
    with pytest.raises(InputError, match="nothere.c3d: no such file"):
        load(tmp_path / "nothere.c3d")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputError, match=r"notes.txt: unknown file type '\.txt'"):
        load(tmp_path / "notes.txt")
    (tmp_path / "dir.c3d").mkdir()
    with pytest.raises(InputError, match="dir.c3d: not a regular file"):
        load(tmp_path / "dir.c3d")
    # Errors are ValueErrors too, for callers that catch the builtin.
    assert issubclass(InputError, ValueError)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.c3d", "notes.txt"]
