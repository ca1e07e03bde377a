"""What a user is told about reading: short TRC rows, what a load dropped or renamed,
the unit advice, ``--units``/``--up-axis``, and trials with different markers (issue 45,
items 4, 5 and 7). Through ``jaxskel.cli.main`` where the command line is the subject;
the fit itself is never run (every case is decided before it).
"""

from __future__ import annotations

from pathlib import Path

import ezc3d
import numpy as np
import pytest

import jaxskel
from jaxskel import InputError, Trial, UnitsWarning, load, save_trial
from jaxskel.cli import main
from jaxskel.io import load_report
from jaxskel.pipeline._plan import check_marker_sets, check_units


def _body(n_frames=60, labels=None, seed=0) -> Trial:
    """An upright cloud of 14 markers (metres), z up."""
    rng = np.random.default_rng(seed)
    labels = labels or [f"M{i}" for i in range(14)]
    x = rng.normal(0, 0.3, (n_frames, len(labels), 3)) + [0.0, 0.0, 1.0]
    return Trial(x, labels, 100.0, up_axis="z")


def _edit_rows(path: Path, edit) -> Path:
    """Apply ``edit`` to every data row of a TRC written by jaxskel (rows start at line 7)."""
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:6] + [edit(line) for line in lines[6:]]) + "\n")
    return path


class _Stop(InputError):
    pass


@pytest.fixture
def fitted(monkeypatch):
    """Replaces the fit: records the trials the CLI hands it, and stops there."""
    seen: list[Trial] = []

    def fit_skeleton(trials, **_):
        seen.extend(trials)
        print("FIT STARTS")
        raise _Stop("stopped before the fit")

    monkeypatch.setattr(jaxskel, "fit_skeleton", fit_skeleton)
    return seen


# ------------------------------------------------------------------ item 5: short rows, the report
def test_trc_rows_that_end_early_are_gaps_and_the_empty_marker_is_reported(tmp_path):
    """A tab-separated row that ends before the last marker's columns leaves that marker
    missing in its frame; when every row does, the marker has no sample, and the load says
    so (the fit's cleaning drops it: it used to vanish without a word)."""
    path = save_trial(_body(), tmp_path / "short.trc")
    _edit_rows(path, lambda line: "\t".join(line.split("\t")[:-3]))  # no row reaches M13
    trial = load(path)
    assert trial.labels[-1] == "M13" and np.isnan(trial.positions[:, -1]).all()
    np.testing.assert_allclose(trial.positions[:, :-1], _body().positions[:, :-1], atol=1e-9)
    assert trial.metadata["empty_labels"] == {"M13": "every data row ends before its columns"}
    assert trial.metadata["short_rows"] == 60
    assert load_report(trial.metadata) == [
        "1 marker without a sample, dropped by the fit: M13 (every data row ends before its columns)",
        "60 data rows end before the last marker's columns (the markers past the end are missing in those frames)",
    ]


def test_trc_row_separated_by_spaces_with_a_missing_value_is_refused_not_shifted(tmp_path):
    """Separated by spaces, an empty cell disappears and every later value moved one marker
    to the left: M0 took M1's values and M13 was lost."""
    path = save_trial(_body(), tmp_path / "spaces.trc")
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:6] + [" ".join(line.split("\t")) for line in lines[6:]]) + "\n")
    np.testing.assert_allclose(load(path).positions, _body().positions, atol=1e-9)  # complete rows read fine

    cells = lines[6].split("\t")
    cells[2:5] = ["", "", ""]  # M0 missing in the first frame
    lines[6] = " ".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"spaces.trc, line 7: 41 values where 44 are expected .* in a row separated "
                                         r"by spaces a missing value cannot be told from a shifted one"):
        load(path)


def test_load_report_names_dropped_renamed_and_prefixed_points(tmp_path):
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    labels = ("Sub:LASI", "Sub:LASI", "Sub:RASI", "Sub:LFEO", "", "*3", "Sub:C7", "Sub:T10")
    c3d["parameters"]["POINT"]["LABELS"]["value"] = labels
    data = np.ones((4, len(labels), 20))
    data[:3] = np.random.default_rng(0).normal(500, 200, (3, len(labels), 20))
    c3d["data"]["points"] = data
    c3d.add_parameter("POINT", "UNITS", ["mm"])
    c3d.write(str(tmp_path / "vicon.c3d"))
    trial = load(tmp_path / "vicon.c3d", drop_unlabeled=True)
    assert load_report(trial.metadata) == [
        "dropped 2 points: Sub:LFEO (Plug-in-Gait segment point); *3 (unlabeled)",
        "renamed 2 labels: 'Sub:LASI #1' -> LASI_2 (repeated label), '' -> point3 (blank label)",
        "removed the subject prefix 'Sub' from the labels",
    ]
    assert load_report(_body().metadata) == []


def test_cli_fit_prints_what_loading_changed_before_the_fit(tmp_path, capsys, fitted):
    path = save_trial(_body(), tmp_path / "short.trc")
    _edit_rows(path, lambda line: "\t".join(line.split("\t")[:-3]))
    assert main(["fit", str(path), "-o", str(tmp_path / "out.h5")]) == 2
    out = capsys.readouterr().out
    report = f"{path}: 1 marker without a sample, dropped by the fit: M13 (every data row ends before its columns)"
    assert report in out and out.index(report) < out.index("FIT STARTS")
    assert main(["fit", str(path), "-o", str(tmp_path / "out.h5"), "--quiet"]) == 2
    assert report not in capsys.readouterr().out
    assert main(["info", str(path)]) == 0
    assert report in capsys.readouterr().out


# ------------------------------------------------------------------ item 4: units, --units, --up-axis
def _stating(path: Path, unit: str) -> Path:
    """A jaxskel TRC (values in mm) rewritten to state ``unit``."""
    text = path.read_text().replace("\tmm\t", f"\t{unit}\t", 1)
    path.write_text(text)
    return path


def test_unit_advice_names_the_unit_and_the_flag(tmp_path, capsys):
    mm_said_m = _stating(save_trial(_body(), tmp_path / "mm_said_m.trc"), "m")
    assert main(["fit", str(mm_said_m), "-o", str(tmp_path / "a.h5")]) == 2
    err = capsys.readouterr().err
    assert "mm_said_m.trc: the markers span 1.21e+03 m per frame, too large for a body or a lab linkage (2 cm to " \
           "40 m): its values were read as metres (as the file states m), but they look like millimetres. Give the " \
           "unit: --units mm on the command line (jaxskel fit, fit-batch, info), or jaxskel.load(path, " \
           "units='mm') in Python" in err
    assert "kilometres" not in err and "Load files with jaxskel.load" not in err

    m_said_mm = save_trial(_body().replace(positions=_body().positions / 1000), tmp_path / "m_said_mm.trc")
    with pytest.raises(InputError, match=r"span 1.21 mm per frame, too small .* read as millimetres \(as the file "
                                         r"states mm\), but they look like metres. Give the unit: --units m on"):
        check_units(load(m_said_mm))
    with pytest.raises(InputError, match=r"\(as given by --units mm / units='mm'\), but they look like metres"):
        check_units(load(m_said_mm, units="mm"))

    in_python = _body().replace(positions=_body().positions * 1000)
    with pytest.raises(InputError, match=r"they look like millimetres. Trial positions are metres: multiply them by "
                                         r"0.001 \(trial.replace\(positions=trial.positions \* 0.001\)\)"):
        check_units(in_python)
    saved = save_trial(in_python, tmp_path / "saved_in_mm.h5")
    with pytest.raises(InputError, match=r"saved_in_mm.h5: .* An HDF5 trial holds the positions as they were saved, "
                                         r"in metres; these were saved in another unit: scale them"):
        check_units(load(saved))


def test_units_warning_says_how_to_give_the_unit(tmp_path):
    path = save_trial(_body(), tmp_path / "nounit.trc")
    path.write_text(path.read_text().replace("\tmm\t", "\t\t", 1))
    with pytest.warns(UnitsWarning, match=r"does not state its length unit; assuming millimetres.* If that is wrong, "
                                          r"give the unit: --units mm \(or cm, m, ...\) on the command line, or "
                                          r"jaxskel.load\(path, units='mm'\) in Python"):
        load(path)
    path.write_text(path.read_text().replace("\t\t100\t1", "\tfurlong\t100\t1", 1))
    with pytest.raises(InputError, match=r"states the length unit 'furlong', which jaxskel does not know .* give the "
                                         r"unit of its values: --units mm"):
        load(path)


def test_cli_units_and_up_axis_reach_the_loader(tmp_path, capsys, fitted):
    mm_said_m = _stating(save_trial(_body(), tmp_path / "mm_said_m.trc"), "m")
    trial_h5 = save_trial(_body(), tmp_path / "saved.h5")
    assert main(["fit", str(mm_said_m), str(trial_h5), "-o", str(tmp_path / "a.h5"), "--units", "mm",
                 "--up-axis=-y", "--quiet"]) == 2
    assert "stopped before the fit" in capsys.readouterr().err
    trc, h5 = fitted
    np.testing.assert_allclose(trc.positions, _body().positions, atol=1e-9)
    assert trc.metadata["units_source"] == "argument" and trc.metadata["original_units"] == "mm"
    assert trc.up_axis == "-y" and h5.up_axis == "-y"  # no unit for the HDF5 trial: always metres

    assert main(["info", str(mm_said_m), "--units", "cm", "--up-axis", "y"]) == 0
    assert "'original_units': 'cm', 'units_source': 'argument'" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["info", str(mm_said_m), "--units", "furlong"])
    assert "unknown length unit 'furlong'" in capsys.readouterr().err


def test_fit_batch_units_reach_the_loader(tmp_path, capsys):
    folder = tmp_path / "in"
    folder.mkdir()
    save_trial(_body().replace(positions=_body().positions / 1000), folder / "m_said_mm.trc")
    assert main(["fit-batch", str(folder), "-o", str(tmp_path / "out"), "--quiet"]) == 1
    assert "(as the file states mm), but they look like metres. Give the unit: --units m" in capsys.readouterr().err
    assert main(["fit-batch", str(folder), "-o", str(tmp_path / "out"), "--quiet", "--units", "mm"]) == 1
    assert "(as given by --units mm / units='mm'), but they look like metres" in capsys.readouterr().err
    with pytest.raises(InputError, match="unknown length unit 'furlong'"):
        jaxskel.fit_batch(folder, tmp_path / "out", units="furlong")


# ------------------------------------------------------------------ item 7: different marker sets
def test_trials_with_different_markers_are_refused_before_the_fit(tmp_path, capsys):
    a = save_trial(_body(), tmp_path / "a.trc")
    b = save_trial(_body(labels=[f"X_M{i}" for i in range(12)] + ["M12", "M13"], seed=1), tmp_path / "b.trc")
    assert main(["fit", str(a), str(b), "-o", str(tmp_path / "ab.h5"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert (
        "the trials fitted together have different markers (they are matched by label, and no trial has all of "
        f"them): {a} lacks X_M0, X_M1, X_M2, X_M3, X_M4, X_M5, X_M6, X_M7 and 4 more (in {b}); {b} lacks M0, M1, "
        f"M2, M3, M4, M5, M6, M7 and 4 more (in {a}). Fit them separately, rename the markers to match, or keep "
        "the markers they share (Trial.select_markers)" in err
    )
    assert not (tmp_path / "ab.h5").exists()


def test_a_trial_may_lack_markers_another_has():
    """A motion trial without the calibration trial's extra markers, or with a marker lost,
    fits with them; unlabelled trajectories differ between recordings and do not count."""
    full = _body()
    check_marker_sets([full, _body(labels=[f"M{i}" for i in range(12)])])
    check_marker_sets([_body(labels=[f"M{i}" for i in range(13)] + ["*1"]), full.replace(labels=(*full.labels[:13], "*7"))])
    check_marker_sets([full])
    with pytest.raises(InputError, match=r": trial 1 lacks M0 \(in trial 2\); trial 2 lacks M13 \(in trial 1\)\."):
        check_marker_sets([_body(labels=[f"M{i}" for i in range(1, 14)]), _body(labels=[f"M{i}" for i in range(13)])])
