"""Label merging inside fit_skeleton: a relabelled passive recording gives the clean-data skeleton."""

import numpy as np
import pytest
from helpers import partition

import jaxskel
from jaxskel import synth


def test_relabelled_body_gives_exact_segmentation_and_topology(tmp_path):
    body = synth.full_body(seed=4)
    trial, truth = synth.simulate(
        body, duration=30.0, seed=4, noise=0.001, gaps=2, relabel=True, ghosts=5
    )
    assert trial.n_markers > 2 * len(truth.physical_labels)  # many more labels than markers
    result = jaxskel.fit_skeleton(trial, rigid=False, ik=False)
    assert result.label_mapping is not None
    # every physical marker's labels land in one merged marker, on the right segment
    phys = result.physical_input()
    real = truth.physical >= 0
    for p in np.unique(truth.physical[real]):
        merged = set(phys[truth.physical == p].tolist()) - {-1}
        assert len(merged) == 1, p
    seg_true = {}
    for lab, p in zip(trial.labels, truth.physical):
        if p >= 0:
            seg_true.setdefault(int(phys[trial.labels.index(lab)]), int(truth.marker_segment[trial.labels.index(lab)]))
    fitted = partition(result.trial.labels, result.segmentation.marker_segment)
    expected = partition(result.trial.labels, [seg_true.get(i, -1) for i in range(result.trial.n_markers)])
    assert fitted == expected
    m = {}
    for s in range(result.n_segments):
        members = [seg_true[i] for i in np.flatnonzero(result.segmentation.marker_segment == s)]
        m[s] = int(np.bincount(members).argmax())
    assert {frozenset((m[int(a)], m[int(b)])) for a, b in result.edges} == {
        frozenset(map(int, e)) for e in truth.edges
    }
    # the result file records the physical marker of every input label
    result.save(tmp_path / "r.h5")
    back = jaxskel.load_result(tmp_path / "r.h5")
    np.testing.assert_array_equal(back.markers.physical, phys)


def test_named_recording_with_occlusions_is_not_merged_by_default():
    trial, _ = synth.simulate(synth.linkage(), duration=10.0, seed=1, noise=0.001)
    x = np.array(trial.positions)
    n = trial.n_frames
    x[: n // 2, 0] = np.nan  # marker 0 only in the second half...
    x[n // 2 :, 3] = np.nan  # ...marker 3 only in the first: no frame has all 9
    gappy = trial.replace(positions=x)
    with pytest.warns(jaxskel.DegenerateMotionWarning, match="not merged"):
        result = jaxskel.fit_skeleton(gappy, rigid=False, ik=False)
    assert result.label_mapping is None and result.trial.n_markers == 9


def test_labels_cleaned_away_before_merging_keep_the_input_order(tmp_path):
    """A passive recording with a slot that is never seen and a label stored twice:
    cleaning drops both before the label merge, so the merge covers fewer labels than
    the input. Every input label still gets its physical marker (the copy its
    original's, the empty slot -1) and the result file is written (it raised an
    IndexError before)."""
    trial, _ = synth.simulate(synth.linkage(), duration=15.0, seed=2, noise=0.001, gaps=2, relabel=True)
    x = np.concatenate([trial.positions, np.full((trial.n_frames, 1, 3), np.nan), trial.positions[:, :1]], 1)
    raw = jaxskel.Trial(x, (*trial.labels, "*999", "*998"), trial.rate)
    result = jaxskel.fit_skeleton(raw, rigid=False, ik=False, merge_labels=True)
    assert result.cleaning.dropped["*999"] == "never present"
    assert result.cleaning.duplicates == {"*998": trial.labels[0]}
    phys = result.physical_input()
    assert len(phys) == raw.n_markers and phys[-2] == -1 and phys[-1] == phys[0] >= 0
    segment = result.marker_segment_input()
    assert segment[-2] == -1 and segment[-1] == segment[0] >= 0
    result.save(tmp_path / "r.h5")
    np.testing.assert_array_equal(jaxskel.load_result(tmp_path / "r.h5").markers.physical, phys)
