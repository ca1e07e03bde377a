"""Which markers the segmentation leaves out of the skeleton on the shared real recordings.

``jaxskel.segment.left_out_markers`` on each recording (or static + dynamic pair), with the
recording's white noise and the default segmentation settings; and the still trials
(``jaxskel.segment.still_trials``) of the pairs. Prints each left-out marker with its reason.

Usage::

    python bench/left_out.py            # ~1 min on 2 cores
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jaxskel
from jaxskel.segment import combine_trials, left_out_markers, still_trials, white_noise

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
CASES = {
    "Hamner static + running": ["opensim_models/Hamner/subject02_static.trc",
                                "opensim_models/Hamner/subject02_running.trc"],
    "Hamner static alone": ["opensim_models/Hamner/subject02_static.trc"],
    "biobuddy anatomical posture + right hip": ["biobuddy/lower_limb_calibration/anatomical_posture.c3d",
                                               "biobuddy/lower_limb_calibration/Test_func_rhip.c3d"],
    "biobuddy calibration set (2 static postures + 7 functional trials)": [
        f"biobuddy/lower_limb_calibration/{name}.c3d" for name in (
            "anatomical_posture", "Test_func_anat", "Test_func_lhip", "Test_func_rhip", "Test_func_lknee",
            "Test_func_rknee", "Test_func_lankle", "Test_func_rankle", "Test_func_trunk")],
    "biobuddy right_hip (planted feet)": ["biobuddy/functional_trials/right_hip.c3d"],
    "pyCGM Movement_trial": ["pycgm/Movement_trial.c3d"],
    "KneeltoProne01": ["auto_marker_label/KneeltoProne01.c3d"],
    "raw unlabelled Pronetokneel01": ["auto_marker_label/S01_Pronetokneel01_mksrem.c3d"],
    "CMU 02_05": ["nimblephysics/cmu_02_05.c3d"],
    "CMU 01_01": ["c3d_to_xyz_cmu/01_01.c3d"],
    "numediart 85_12": ["numediart/85_12.c3d"],
    "HDM05 bd": ["numediart/HDM_bd_05-01_01_120.c3d"],
    "basket sprint": ["kineticstoolkit/kinematics_basket_sprint.c3d"],
}


def main() -> int:
    for name, files in CASES.items():
        trials = [jaxskel.load(DATA / f, **({"units": "mm"} if "mksrem" in f else {})) for f in files]
        trial = combine_trials(trials)
        t0 = time.perf_counter()
        noise = white_noise(trial.positions)
        left = left_out_markers(trial, white_noise=noise)
        bounds = tuple(trial.metadata.get("trial_bounds", ((0, trial.n_frames),)))
        still = still_trials(trial, bounds, white_noise=noise)
        print(f"{name}: {trial.n_markers} markers, {len(left.labels)} left out, still trials {list(still)} "
              f"({time.perf_counter() - t0:.2f} s)")
        for label, why in left.reasons.items():
            print(f"    {label}: {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
