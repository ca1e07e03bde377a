"""The SD06 stages through saved exported programs (the jaxskel command's program cache) give the plain results."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from jaxskel import synth
from jaxskel._runtime import program_cache
from jaxskel.sd06 import parameterize_arrays


def test_saved_programs_give_the_same_parameterisation(tmp_path):
    body = synth.full_body(seed=0)
    _, truth = synth.simulate(body, "calibration", duration=4.0, rate=60.0, seed=0)
    rot = truth.segment_rotations
    quats = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(*rot.shape[:2], 4)

    def run():
        return parameterize_arrays(truth.joint_positions, body.edges, quats, root=body.root,
                                   segment_translations=truth.segment_translations, rate=60.0)

    plain = run()
    try:
        program_cache.set_directory(tmp_path)
        saved = run()  # exports and saves the programs
        program_cache.set_directory(tmp_path)  # forget the in-process programs: load them from disk
        loaded = run()
    finally:
        program_cache.set_directory(None)
    assert len(list(tmp_path.glob("*.jaxexport"))) == 4  # the normalisation and the three stages
    for other in (saved, loaded):
        np.testing.assert_array_equal(other.n_axes, plain.n_axes)
        np.testing.assert_allclose(other.axes, plain.axes, atol=1e-9)
        np.testing.assert_allclose(other.angles, plain.angles, atol=1e-9)
        np.testing.assert_allclose(other.normalization.limb_frames, plain.normalization.limb_frames, atol=1e-9)
        assert other.normalization.default_frame == plain.normalization.default_frame
