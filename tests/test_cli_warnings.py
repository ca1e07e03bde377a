"""Issue 45, item 6: the command line's warnings each start a line of their own (the
progress bar is cleared, and the message begins with a newline where stderr is not a
terminal), and a warning of `jaxskel fit-batch` names its trial, in process and on a
Dask cluster: ``jaxskel: warning (Category) [trial]: message``. Before, a warning
continued the progress bar's line, a batch showed one unnamed warning for two trials
(Python's once-per-code-location rule hid the second) and Dask workers printed theirs
raw.

The recordings: a linkage whose markers 0 and 4 are each missing for half of it, so
no frame shows all of its 9 labels; the labels are named, so they are not merged and
the fit warns about it (one warning per trial, early in the fit)."""

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.cli import main

MERGE = ("this recording has more labels than markers in any frame, but its labels are named, so labels were not "
         "merged; pass merge_labels=True (CLI: --merge-labels yes) if it comes from a passive system that relabels "
         "markers after occlusions")


@pytest.fixture(scope="module")
def gappy(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gappy")
    for i in range(2):
        trial, _ = synth.simulate(synth.linkage(), duration=6.0 + i, seed=21 + i, noise=0.001)
        x = trial.positions.copy()
        half = trial.n_frames // 2
        x[:half, 0] = np.nan
        x[half:, 4] = np.nan
        jaxskel.save_trial(trial.replace(positions=x), folder / f"g{i}.c3d")
    return folder


def warning_lines(err: str) -> list[str]:
    """The warnings in ``err``, each checked to start a line (not to follow a bar's text)."""
    out = []
    start = err.find("jaxskel: warning")
    while start >= 0:
        assert start == 0 or err[start - 1] == "\n", repr(err[max(0, start - 80) : start + 40])
        out.append(err[start:].split("\n", 1)[0])
        start = err.find("jaxskel: warning", start + 1)
    return out


def test_a_warning_starts_its_own_line_below_the_progress_bar(gappy, tmp_path, capsys):
    assert main(["fit", str(gappy / "g0.c3d"), "-o", str(tmp_path / "g0.h5"), "--no-rigid"]) == 0
    err = capsys.readouterr().err
    assert "fit_skeleton:" in err  # the bar was drawn
    assert warning_lines(err) == [f"jaxskel: warning (DegenerateMotionWarning): {MERGE}"]


def test_fit_batch_names_the_trial_of_each_warning(gappy, tmp_path, capsys):
    assert main(["fit-batch", str(gappy), "-o", str(tmp_path / "out"), "--no-rigid"]) == 0
    err = capsys.readouterr().err
    assert "fit_batch:" in err
    assert sorted(warning_lines(err)) == [
        f"jaxskel: warning (DegenerateMotionWarning) [g{i}]: {MERGE}" for i in range(2)
    ]


def test_the_api_keeps_each_trials_warnings_and_warns_them_naming_the_trial(gappy):
    with pytest.warns(jaxskel.DegenerateMotionWarning) as caught:
        batch = jaxskel.fit_batch(gappy, rigid=False)
    assert [o.warnings for o in batch] == [((jaxskel.DegenerateMotionWarning, MERGE),)] * 2
    said = sorted((w.message.trial, w.message.text, str(w.message)) for w in caught)
    assert said == [(f"g{i}", MERGE, f"[g{i}] {MERGE}") for i in range(2)]


def test_dask_workers_warnings_reach_the_command_line_naming_the_trial(gappy, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        args = ["fit-batch", str(gappy), "-o", str(tmp_path / "out"), "--no-rigid", "--quiet"]
        assert main([*args, "--scheduler", cluster.scheduler_address]) == 0
    err = capsys.readouterr().err
    assert sorted(warning_lines(err)) == [
        f"jaxskel: warning (DegenerateMotionWarning) [g{i}]: {MERGE}" for i in range(2)
    ]
    assert "UserWarning" not in err and "warnings.warn" not in err
