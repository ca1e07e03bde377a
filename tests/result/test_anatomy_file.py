"""``/anatomy`` in a result file: written and read back as the same Anatomy record."""

from __future__ import annotations

import h5py
import numpy as np

from jaxskel.anatomy import Anatomy
from jaxskel.result._anatomy_file import load_anatomy, read_anatomy, write_anatomy


def test_an_anatomy_round_trips_through_its_group(tmp_path):
    anatomy = Anatomy(parts=("pelvis", "", "thigh_l"), confidence=[0.9, 0.0, 0.75], humanoid=True,
                      up=[0.0, 0.0, 1.0], front=[0.0, -1.0, 0.0], notes=("legs matched by length",))
    path = tmp_path / "a.h5"
    with h5py.File(path, "w") as f:
        f.attrs["schema_version"] = 1
        write_anatomy(f.create_group("anatomy"), anatomy)
    back = load_anatomy(path)
    assert back.parts == anatomy.parts and back.humanoid and back.notes == anatomy.notes
    np.testing.assert_array_equal(back.confidence, anatomy.confidence)
    np.testing.assert_array_equal(back.left, [1.0, 0.0, 0.0])  # up x front, recomputed from what was stored
    with h5py.File(path, "a") as f:
        del f["anatomy"]
        assert read_anatomy(f) is None  # a file from a fit that did not name the body
