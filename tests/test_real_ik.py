"""IK residuals of the whole fit on real recordings (Kirk et al. §3.3 on real data).

OpenSim's rule of thumb for a good marker fit is an RMS marker error under 2 cm with
no marker over 4 cm. For every recording this fits the skeleton with the defaults,
runs IK over all frames and asserts that the per-frame marker RMS has a median under
2 cm and a 95th percentile under 4 cm; the figures are printed (``pytest -s``) and
attached to the test report (``record_property``).

Measured (2-core CPU, 2026-11-21): KneeltoProne01 median 6.7 / p95 10.0 / max 13.0 mm;
PronetoRun01 1.8 / 23.6 / 30.6 mm (the subject leaves the volume at the end);
CMU 02_05 13.3 / 24.2 / 31.0 mm (knee markers: thigh and shank are grouped as one
segment, so a "rigid" segment bends; see issue 3's notes).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import REAL

import jaxskel

RECORDINGS = {
    "KneeltoProne01 (bundled)": None,
    "PronetoRun01": "auto_marker_label/PronetoRun01.c3d",
    "cmu_02_05": "nimblephysics/cmu_02_05.c3d",
}


@pytest.mark.parametrize("name", list(RECORDINGS))
def test_ik_residuals_on_real_recordings(name, record_property):
    rel = RECORDINGS[name]
    if rel is None:
        trial = jaxskel.load_sample()
    else:
        if not (REAL / rel).is_file():
            pytest.skip("needs ../shared/data/real")
        trial = jaxskel.load(REAL / rel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxskel.ConvergenceWarning)
        result = jaxskel.fit_skeleton(trial)
    motion = result.motion
    assert motion is not None and motion.n_frames == result.trial.n_frames
    rms = np.asarray(motion.marker_rms) * 1e3
    seen = np.isfinite(rms)
    assert seen.mean() > 0.95, "IK must give a residual for (almost) every frame"
    median, p95, worst = np.median(rms[seen]), np.percentile(rms[seen], 95), rms[seen].max()
    figures = {"median_mm": round(float(median), 2), "p95_mm": round(float(p95), 2), "max_mm": round(float(worst), 2),
               "segments": result.segmentation.n_segments, "frames": int(motion.n_frames)}
    record_property("ik_marker_rms", figures)
    print(f"\n{name}: IK marker RMS per frame {figures}")
    assert median < 20.0, f"median marker RMS {median:.1f} mm is over OpenSim's 2 cm rule of thumb"
    assert p95 < 40.0, f"95th percentile marker RMS {p95:.1f} mm is over 4 cm"
    # gap filling: frames with missing markers still get every segment posed
    assert np.isfinite(motion.joint_positions).all()
