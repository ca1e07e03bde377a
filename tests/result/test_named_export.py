"""Exports of a fitted, named humanoid: a BVH Blender reads as an upright T-posed Mixamo rig,
labels that are not ASCII, and the joint centres as virtual markers in a TRC.

One fit (module scope) of 2 s of the synthetic full body (jaxskel.synth.full_body: Z up,
facing +X, so its left is +Y), two of whose markers are relabelled ``Kné€`` and ``L+R``.
Its anatomy is the synthetic truth (tests/anatomy/truth.py), not jaxskel's own naming,
so these tests check the exporters alone.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.anatomy import Anatomy
from jaxskel.result import export_bvh, read_bvh
from jaxskel.result._bvh import bvh_frame
from jaxskel.result._export_names import MIXAMO, ascii_names
from jaxskel.result._virtual import fitted_markers_trial, with_joint_centres
from jaxskel.segment import segment_names

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from anatomy.truth import synth_truth

PROBE = Path(__file__).with_name("blender_bvh_probe.py")
RENAMED = {"LKNE": "Kné€", "RKNE": "L+R"}


@dataclasses.dataclass(frozen=True)
class Named:
    body: object
    truth: object
    result: object
    anatomy: Anatomy


@pytest.fixture(scope="module")
def named() -> Named:
    body = synth.full_body(seed=0)
    trial, truth = synth.simulate(body, motion="calibration", duration=2.0, rate=50.0, noise=0.0005, seed=0)
    renamed = trial.replace(labels=tuple(RENAMED.get(v, v) for v in trial.labels))
    result = jaxskel.fit_skeleton(renamed, len(truth.segment_names))
    parts = synth_truth(body, trial.labels, result.segmentation.marker_segment)
    anatomy = Anatomy(parts=tuple(p or "" for p in parts), confidence=np.ones(len(parts)), humanoid=True,
                      up=(0, 0, 1), front=(1, 0, 0))
    return Named(body, truth, result, anatomy)


def _proximal(skeleton) -> np.ndarray:
    prox = np.full(skeleton.n_segments, -1)
    prox[skeleton.edges[:, 1]] = np.arange(skeleton.n_joints)
    return prox


def test_the_synthetic_body_faces_x_with_its_left_at_y(named):
    """The anatomy's up and front are right: the left pelvis and knee markers lie at +Y of the
    right ones, the head above the pelvis, the toes in front of the heels (+X)."""
    r = named.result
    rest = int(r.skeleton.diagnostics.get("rest_frame", 0))
    at = dict(zip(r.trial.labels, r.trial.positions[rest]))
    assert at["LASI"][1] - at["RASI"][1] > 0.05 and at["Kné€"][1] - at["L+R"][1] > 0.05
    assert at["LFHD"][2] > at["LASI"][2] + 0.3
    assert at["LTOE"][0] - at["LHEE"][0] > 0.05


def test_a_non_ascii_label_fits_and_exports(named, tmp_path):
    r = named.result
    by_markers = segment_names(r.segmentation.groups)  # the fit names the segments after the body parts
    assert any("Kné€" in n for n in by_markers) and any("L+R" in n for n in by_markers)
    for path, kwargs in ((tmp_path / "labels.bvh", {}),
                         (tmp_path / "named.bvh", {"anatomy": named.anatomy, "names": "labels"})):
        export_bvh(r.skeleton, r.motion, path, rate=r.trial.rate, labels=by_markers, **kwargs)
        path.read_bytes().decode("ascii")  # raises if any byte is not ASCII
        data = read_bvh(path)
        assert sorted(data.names) == sorted(ascii_names(by_markers))
        assert all(n.isidentifier() for n in data.names)
        assert any("Kne" in n for n in data.names) and any("L_R" in n for n in data.names)
    # the result's own export (its named body: Mixamo names) writes an ASCII file too
    path = r.export_bvh(str(tmp_path / "result.bvh"))
    path.read_bytes().decode("ascii")
    assert all(n.isidentifier() for n in read_bvh(path).names)


def _clean_env() -> dict[str, str]:
    """This run's environment without PYTHONPATH/PYTHONHOME (they would lead Blender's Python to numpy 2)."""
    import os

    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def _blender(python: str, path: Path, frames: list[int]) -> dict:
    done = subprocess.run([python, str(PROBE), str(path), *map(str, frames)], capture_output=True, text=True,
                          env=_clean_env(), timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    line = next(v for v in done.stdout.splitlines() if v.startswith("PROBE-JSON "))
    return json.loads(line[len("PROBE-JSON "):])


def test_blender_reads_an_upright_t_posed_mixamo_rig_at_the_fitted_joints(named, blender_python, tmp_path):
    """Blender's importer, default options (axes: BVH (x, y, z) -> Blender (x, -z, y); scale 1,
    so centimetres; frames from 1)."""
    r, anatomy = named.result, named.anatomy
    skeleton, motion = r.skeleton, r.motion
    path = export_bvh(skeleton, motion, tmp_path / "rig.bvh", rate=r.trial.rate, anatomy=anatomy)
    n_frames = motion.n_frames
    frames = [1, n_frames // 2, n_frames]
    out = _blender(blender_python, path, frames)

    # Names: Mixamo's, the thorax "Spine" (this body has no abdomen); the tree kept.
    mixamo = {**MIXAMO, "thorax": "Spine"}
    expected = [mixamo[p] for p in anatomy.parts]
    assert sorted(out["bones"]) == sorted(expected)
    parent_of = dict(zip(out["bones"], out["parents"]))
    for s, p in enumerate(skeleton.parent):
        assert parent_of[expected[s]] == (expected[p] if p >= 0 else None)

    # Rest: upright T-pose, facing Blender's -Y (BVH +Z), the subject's left at +X.
    head = dict(zip(out["bones"], np.asarray(out["rest_heads"])))
    tail = dict(zip(out["bones"], np.asarray(out["rest_tails"])))
    tol = 0.05  # cm: Blender keeps float32
    assert head["Head"][2] > head["Spine"][2] > head["Hips"][2]
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        arm = [head[f"{side}{b}"] for b in ("Arm", "ForeArm", "Hand")]
        np.testing.assert_allclose([a[1:] for a in arm], [arm[0][1:]] * 3, atol=tol)  # level, in line
        assert sign * arm[0][0] > 0 and all(sign * (b[0] - a[0]) > 20.0 for a, b in itertools.pairwise(arm))
        assert abs(head["Head"][2] - arm[0][2]) < 15.0  # shoulders near the neck's height
        leg = [head[f"{side}{b}"] for b in ("UpLeg", "Leg", "Foot")]
        np.testing.assert_allclose([a[:2] for a in leg], [leg[0][:2]] * 3, atol=tol)  # straight down
        assert all(a[2] - b[2] > 30.0 for a, b in itertools.pairwise(leg)) and leg[0][2] < head["Hips"][2]
        foot = tail[f"{side}Foot"] - head[f"{side}Foot"]
        assert foot[1] < -5.0 and abs(foot[0]) < tol  # forward (-Y in Blender), not sideways
    # The fitted bones' lengths: every parent head to child head.
    origin = np.zeros((skeleton.n_segments, 3))
    origin[skeleton.edges[:, 1]] = skeleton.joint_offsets[:, 1]
    for j, (p, c) in enumerate(skeleton.edges.tolist()):
        length = 100.0 * np.linalg.norm(skeleton.joint_offsets[j, 0] - origin[p])
        assert np.linalg.norm(head[expected[c]] - head[expected[p]]) == pytest.approx(length, abs=tol)

    # Frames 1..F, and each bone's head at the fitted joint (the root: its origin), within 5 mm.
    assert out["frame_range"] == [1.0, float(n_frames)]
    c = bvh_frame(anatomy)
    prox = _proximal(skeleton)
    for frame in frames:
        f = frame - 1
        fit = np.where((prox >= 0)[:, None], motion.joint_positions[f, np.maximum(prox, 0)],
                       motion.root_position[f][None])
        bvh_cm = 100.0 * fit @ c.T
        blender = np.stack([bvh_cm[:, 0], -bvh_cm[:, 2], bvh_cm[:, 1]], axis=1)
        got = dict(zip(out["bones"], np.asarray(out["heads"][str(frame)])))
        err = np.array([np.linalg.norm(got[expected[s]] - blender[s]) for s in range(skeleton.n_segments)])
        assert err.max() < 0.5, (frame, err)


def _true_joint(truth, child_name: str) -> int:
    return int(np.flatnonzero(truth.edges[:, 1] == truth.segment_names.index(child_name))[0])


def test_the_trc_carries_the_joint_centres_as_virtual_markers(named, tmp_path):
    r, anatomy, truth = named.result, named.anatomy, named.truth
    fitted = fitted_markers_trial(r.trial, r.skeleton, r.motion, joint_centres=True, anatomy=anatomy)
    fitted.save(str(tmp_path / "jc.trc"))
    back = jaxskel.load(tmp_path / "jc.trc")
    m = r.trial.n_markers
    assert back.labels[:m] == r.trial.labels  # the non-ASCII labels too
    assert sorted(back.labels[m:]) == sorted(
        ["LHJC", "RHJC", "LKJC", "RKJC", "LAJC", "RAJC", "LSJC", "RSJC", "LEJC", "REJC", "LWJC", "RWJC", "TJC", "NJC"])
    np.testing.assert_allclose(back.positions[:, m:], r.motion.joint_positions, atol=1e-6)  # mm, 6 decimals
    # each label is the joint it names: the fitted centre is the true one
    for label, child in (("RKJC", "r_shank"), ("LHJC", "l_thigh"), ("REJC", "r_forearm"), ("LAJC", "l_foot")):
        true = truth.joint_positions[:, _true_joint(truth, child)]
        err = np.linalg.norm(back.positions[:, back.labels.index(label)] - true, axis=-1)
        assert np.median(err) < 0.02, (label, np.median(err))


def test_joint_centres_without_an_anatomy_are_named_after_their_segment_and_never_shadow_a_marker(named):
    r = named.result
    taken = r.trial.replace(labels=("RHJC", *r.trial.labels[1:]))
    with_anatomy = with_joint_centres(taken, r.skeleton, r.motion, named.anatomy)
    assert "RHJC_2" in with_anatomy.labels and with_anatomy.labels[0] == "RHJC"
    plain = with_joint_centres(r.trial, r.skeleton, r.motion)
    names = ascii_names(r.skeleton.names())
    assert plain.labels[r.trial.n_markers:] == tuple(f"{names[c]}_JC" for c in r.skeleton.edges[:, 1])
    with pytest.raises(jaxskel.InputError, match="frames"):
        with_joint_centres(r.trial.replace(positions=r.trial.positions[:-1]), r.skeleton, r.motion)
