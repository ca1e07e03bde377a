"""No spurious warnings from parameterize on clean synthetic data, for every method (issue 47, item 6)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from sd06_truth import protocol_and_free

from jaxskel import ConvergenceWarning, DegenerateMotionWarning, synth
from jaxskel.sd06 import parameterize_arrays
from jaxskel.sd06._parameterize import METHODS

BODY = synth.full_body(seed=0)


@pytest.fixture(scope="module")
def session():
    """Noise-free protocol (every main movement alone) then 20 s of free movement."""
    return protocol_and_free(BODY, rate=30.0, free_seconds=20.0, seed=1)


def _param(rec, **kw):
    return parameterize_arrays(rec.joints, BODY.edges, rec.quats, root=BODY.root, segment_translations=rec.trans, **kw)


@pytest.mark.parametrize("calibration", ["protocol", None, "auto"])
def test_clean_data_gives_no_warning_with_any_method(session, calibration):
    window = session.protocol if calibration == "protocol" else calibration
    for method in METHODS:
        with warnings.catch_warnings():
            warnings.simplefilter("error", ConvergenceWarning)
            warnings.simplefilter("error", DegenerateMotionWarning)
            param = _param(session, method=method, calibration=window)
        assert param.converged.all() and param.exercised.all()
        assert param.normalization.handedness == "knees"
        if method == "em":
            assert param.steps.max() < param.settings["max_em_steps"]


def test_em_that_cannot_settle_still_warns(session):
    """The warning is real: EM cut off after one step on free movement does not settle."""
    with pytest.warns(ConvergenceWarning, match="EM axis extraction"):
        param = _param(session, method="em", max_em_steps=1)
    assert not param.converged.all() and np.all(param.steps <= 1)
