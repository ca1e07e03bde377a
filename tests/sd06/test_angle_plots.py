"""plot_joint_angles (issue 47, "Examples"): joint-angle panels as clinical gait reports show them.

The parameterisation comes from ground truth (synthetic walk, exact joint centres and
segment rotations, no fitting); 450 frames share the 512-frame bucket of the other
SD06 tests, so a test run compiles the stages once.
"""

from __future__ import annotations

import warnings
from itertools import pairwise

import numpy as np
import pytest
from helpers import matrix_to_quat
from matplotlib.figure import Figure

from jaxskel import InputError, synth
from jaxskel.plots import plot_joint_angles
from jaxskel.sd06 import parameterize_arrays

RATE = 30.0
CAL = (30, 150)  # calibration window (frames): shaded in the time plots


@pytest.fixture(scope="module")
def walk():
    _, truth = synth.simulate(synth.full_body(seed=0), motion="walk", duration=15.0, rate=RATE, seed=0)
    names = list(truth.joint_names)
    hips = {names.index("l_hip"): 2, names.index("r_hip"): 2}  # two axes: "axis 2" curves too
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # wrists and neck barely move in a walk
        param = parameterize_arrays(
            truth.joint_positions, truth.edges, np.asarray(matrix_to_quat(truth.segment_rotations)),
            root=truth.root, segment_translations=truth.segment_translations, calibration=CAL, n_axes=hips,
        )
    return param, names


def _lines(ax):
    return {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}


def test_one_panel_per_joint_with_angles_in_degrees_against_seconds(walk):
    param, names = walk
    chosen = ["l_hip", "l_knee", "l_ankle"]
    fig = plot_joint_angles(param, joints=chosen, names=names, rate=RATE)
    assert isinstance(fig, Figure) and len(fig.axes) == len(chosen)
    time = np.arange(param.n_frames) / RATE
    for ax, name in zip(fig.axes, chosen, strict=True):
        j = names.index(name)
        assert name in ax.get_title() and ax.get_xlabel() == "seconds"
        lines = _lines(ax)
        expected = ["axis 1", "axis 2", "twist"] if param.n_axes[j] == 2 else ["axis 1", "twist"]
        assert sorted(lines) == sorted(expected)
        for label, line in lines.items():
            k = {"axis 1": 0, "axis 2": 1, "twist": 2}[label]
            np.testing.assert_allclose(line.get_xdata(), time)
            np.testing.assert_allclose(line.get_ydata(), np.degrees(param.angles[:, j, k]), rtol=1e-12)
        # the calibration window is shaded: one span from its first to its last frame (+- half a frame)
        spans = [p for p in ax.patches if p.get_label() == "calibration"]
        assert len(spans) == 1
        x0, x1 = (spans[0].get_x(), spans[0].get_x() + spans[0].get_width())
        np.testing.assert_allclose([x0, x1], [(CAL[0] - 0.5) / RATE, (CAL[1] - 0.5) / RATE])
    assert param.n_axes[names.index("l_hip")] == 2


def test_all_joints_and_frames_without_rate(walk):
    param, _ = walk
    fig = plot_joint_angles(param)
    assert len(fig.axes) == param.n_joints
    assert fig.axes[0].get_xlabel() == "frame" and "joint 0" in fig.axes[0].get_title()
    np.testing.assert_array_equal(_lines(fig.axes[3])["axis 1"].get_xdata(), np.arange(param.n_frames))


def test_cycle_mean_over_cycles(walk):
    param, names = walk
    j = names.index("r_hip")
    starts = np.array([12, 45.5, 80, 112, 147, 181, 214])  # fractional frames allowed
    fig = plot_joint_angles(param, joints=[j], rate=RATE, cycle=starts)
    (ax,) = fig.axes
    assert ax.get_xlabel() == "% cycle" and ax.get_xlim() == (0.0, 100.0)
    lines = _lines(ax)
    assert sorted(lines) == ["axis 1", "axis 2", "twist"]
    pct = np.linspace(0, 100, 101)
    frames = np.arange(param.n_frames)
    for label, k in (("axis 1", 0), ("axis 2", 1), ("twist", 2)):
        curves = np.array([
            np.interp(a + (b - a) * pct / 100, frames, np.degrees(param.angles[:, j, k]))
            for a, b in pairwise(starts)
        ])
        np.testing.assert_allclose(lines[label].get_xdata(), pct)
        np.testing.assert_allclose(lines[label].get_ydata(), curves.mean(axis=0), atol=1e-9)
    # the bands: mean +- 1 SD (ddof=1), one filled polygon per curve
    bands = ax.collections
    assert len(bands) == 3
    top = bands[0].get_paths()[0].vertices[:, 1].max()
    k0 = np.array([np.interp(a + (b - a) * pct / 100, frames, np.degrees(param.angles[:, j, 0]))
                   for a, b in pairwise(starts)])
    np.testing.assert_allclose(top, (k0.mean(0) + k0.std(0, ddof=1)).max(), atol=1e-9)
    assert not [p for p in ax.patches if p.get_label() == "calibration"]  # no time axis to shade


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"joints": ["no_such_joint"]}, "unknown joint"),
        ({"joints": [99]}, "unknown joint"),
        ({"joints": ["l_knee"], "names": None}, "unknown joint"),
        ({"joints": []}, "empty"),
        ({"names": ["a", "b"]}, "names must be"),
        ({"rate": 0.0}, "rate"),
        ({"cycle": [10, 500]}, "0..449"),
        ({"cycle": [-1, 30]}, "0..449"),
        ({"cycle": [40, 30]}, "increasing"),
        ({"cycle": [30]}, "at least 2"),
        ({"path": 12}, "path must be"),
        ({"path": "angles.txt"}, "matplotlib cannot write"),
    ],
)
def test_bad_input(walk, kwargs, match):
    param, names = walk
    kwargs = {"names": names, **kwargs}
    with pytest.raises(InputError, match=match):
        plot_joint_angles(param, **kwargs)


def test_writes_the_file_atomically_and_only_with_overwrite(walk, tmp_path):
    param, names = walk
    path = tmp_path / "angles.png"
    fig = plot_joint_angles(param, joints=["l_knee", "r_knee"], names=names, rate=RATE, path=path)
    assert isinstance(fig, Figure) and path.stat().st_size > 5_000
    assert [p.name for p in tmp_path.iterdir()] == ["angles.png"]  # no temporary file left
    with pytest.raises(InputError, match="exists"):
        plot_joint_angles(param, joints=["l_knee"], names=names, path=path)
    plot_joint_angles(param, joints=["l_knee"], names=names, cycle=[10, 40, 70], path=path, overwrite=True)
    assert path.stat().st_size > 5_000
