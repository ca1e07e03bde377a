"""Joint angles against known answers (``python bench/angles.py``).

1. **Synthetic truth.** Noisy synthetic full bodies (``synth.full_body``, calibration motion,
   0.5 mm noise, seeds 0-3) fitted with ``fit_skeleton`` defaults: knee and elbow flexion
   against the generating angles, RMS in degrees.
2. **Plug-in Gait.** ``pycgm/Movement_trial.c3d`` stores Plug-in Gait's own angles as c3d points (``LKneeAngles``:
flexion, adduction, rotation in degrees, PiG's clinical signs). The recording is fitted with
``fit_skeleton`` defaults and named without marker names; for every joint the fit names, each
of its angles is compared with PiG's component of the same meaning: RMS difference, the
mean offset (the two models' neutral frames differ by a constant) and the RMS after it.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import ezc3d
import numpy as np

import jaxskel

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "pycgm" / "Movement_trial.c3d"

#: Our angle -> (PiG point, component); PiG's signs are clinical as ours (flexion, adduction, internal +).
PIG = {}
for side, p in (("l", "L"), ("r", "R")):
    PIG.update({
        f"knee_{side}_flexion": (f"{p}KneeAngles", 0), f"hip_{side}_flexion": (f"{p}HipAngles", 0),
        f"hip_{side}_adduction": (f"{p}HipAngles", 1), f"hip_{side}_internal_rotation": (f"{p}HipAngles", 2),
        f"ankle_{side}_dorsiflexion": (f"{p}AnkleAngles", 0), f"elbow_{side}_flexion": (f"{p}ElbowAngles", 0),
        f"shoulder_{side}_flexion": (f"{p}ShoulderAngles", 0),
    })


def synthetic(seeds=range(4)) -> None:
    from jaxskel import synth

    print("| body seed | knee_l | knee_r | elbow_l | elbow_r | (flexion RMS, deg) |")
    print("|---|---:|---:|---:|---:|---|")
    for seed in seeds:
        body = synth.full_body(seed=seed)
        trial, truth = synth.simulate(body, motion="calibration", duration=8.0, noise=0.0005, seed=seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            angles = jaxskel.fit_skeleton(trial).joint_angles()
        cells = []
        for joint in ("l_knee", "r_knee", "l_elbow", "r_elbow"):
            side, kind = joint.split("_")
            name = f"{kind}_{side}_flexion"
            true = truth.joint_angles[truth.joint_names.index(joint)][:, 0]
            cells.append(f"{np.rad2deg(np.sqrt(np.mean((angles[name] - true) ** 2))):.2f}"
                         if name in angles.names else "not named")
        print(f"| {seed} | {' | '.join(cells)} | |")


def plug_in_gait() -> None:
    c3d = ezc3d.c3d(str(DATA))
    labels = c3d["parameters"]["POINT"]["LABELS"]["value"]
    points = c3d["data"]["points"][:3]  # (3, N, F)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = jaxskel.fit_skeleton(jaxskel.load(DATA))
    angles = result.joint_angles()
    print(f"{DATA.name}: {sum(map(bool, result.anatomy.parts))} of {result.n_segments} segments named; "
          f"{len(angles.names)} angles")
    print("| angle | PiG | RMS (deg) | offset (deg) | RMS less offset (deg) | correlation |")
    print("|---|---|---:|---:|---:|---:|")
    for name, (point, k) in PIG.items():
        if name not in angles.names or point not in labels:
            continue
        pig = points[k, labels.index(point)]
        ours = np.rad2deg(angles[name])
        ok = np.isfinite(pig) & np.isfinite(ours) & (pig != 0)
        d = ours[ok] - pig[ok]
        rms, off = np.sqrt(np.mean(d**2)), np.mean(d)
        corr = np.corrcoef(ours[ok], pig[ok])[0, 1]
        print(f"| {name} | {point}[{k}] | {rms:.1f} | {off:+.1f} | {np.std(d):.1f} | {corr:.3f} |")


def main() -> int:
    synthetic()
    print()
    plug_in_gait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
