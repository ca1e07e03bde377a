"""Growing the automatic segment count after the rigid fit (:meth:`jaxskel.pipeline.StagePlan.grow_count`):
when it grows, which fit is kept, which warnings the user sees. The fits are stubs here;
the end-to-end cases (random trees whose eigengap joins two segments) are in
``test_fit_cli.py``. The tests of the rigid skeleton's reading switch the groups' scatter
off (``skeleton_reading_only``): their trial is a joined pair that the scatter reads too."""

import dataclasses
import warnings

import numpy as np
import pytest

from jaxskel import FitOptions, synth
from jaxskel.pipeline import PreparedFit, StagePlan, _plan
from jaxskel.pipeline._split_refit import MAX_SPLITS, ScatterReading, crowded_nonrigid
from jaxskel.segment import segment_markers


@dataclasses.dataclass
class _Skeleton:
    marker_labels: tuple
    marker_segment: np.ndarray
    nonrigid_markers: tuple


@dataclasses.dataclass
class _Result:
    trial: object
    segmentation: object
    skeleton: object
    settings: dict
    motion: object = None


class _Note(UserWarning):
    pass


@dataclasses.dataclass(frozen=True)
class _Plan(StagePlan):
    """A stage plan whose joint, skeleton and motion stages are stubs: ``first(prep)`` is
    the first fit, ``again(prep)`` every refit, ``moved(prep, result)`` the motion."""

    first: object = None
    again: object = None
    moved: object = None

    def joints(self, prep):
        return "tree"

    def skeleton(self, prep, topology):
        assert topology == "tree"
        return self.first(prep)

    def refit(self, prep):
        return self.again(prep)

    def motion(self, prep, result):
        return self.moved(prep, result) if self.moved is not None else result


def _grow(prep, first, again, moved=None, stacklevel=2, **settings):
    plan = _Plan(FitOptions.from_settings(**settings), first=first, again=again, moved=moved)
    return plan.grow_count(prep, stacklevel=stacklevel)  # as warnings.warn: 2 is _grow, 3 its caller


@pytest.fixture(scope="module")
def trial():
    # the eigengap joins two of its segments (test_fit_cli.py); one more splits them, no marker alone
    trial, _ = synth.simulate(synth.random_tree(12, seed=3), duration=20.0, seed=3, noise=0.001, gaps=2)
    return trial


@pytest.fixture
def skeleton_reading_only(monkeypatch):
    """The split search as if the groups' scatter flagged nothing."""
    monkeypatch.setattr(_plan, "read_scatter", lambda trial, segmentation: ScatterReading((), 0))


def _prep(trial, n_segments=None):
    seg = segment_markers(trial, n_segments)
    return PreparedFit(
        input_labels=trial.labels, trial=trial, cleaning=None, label_mapping=None, segmentation=seg,
        trial_bounds=((0, trial.n_frames),), timings={},
    )


def _result(prep, seg, flagged):
    labels = tuple(prep.trial.labels)
    skeleton = _Skeleton(labels, np.asarray(seg.marker_segment), tuple(flagged))
    return _Result(prep.trial, seg, skeleton, {})


def test_crowded_markers_are_the_flagged_ones_sharing_a_segment():
    labels = ("a", "b", "c", "d", "e", "f")
    sk = _Skeleton(labels, np.array([0, 0, 0, 1, 1, 2]), ("e", "b", "a", "d", "f"))
    assert crowded_nonrigid(sk) == ("a", "b")
    assert crowded_nonrigid(_Skeleton(labels, np.array([0, 0, 0, 1, 1, 2]), ("a", "d", "f"))) == ()
    # both markers of a group of two: a split could only leave them alone, never kept
    assert crowded_nonrigid(_Skeleton(labels, np.array([0, 0, 0, 1, 1, 2]), ("d", "e"))) == ()
    assert crowded_nonrigid(None) == ()


@pytest.mark.usefixtures("skeleton_reading_only")
def test_count_grows_while_a_segment_holds_two_flagged_markers_and_fewer_remain(trial):
    prep = _prep(trial)
    m0 = prep.segmentation.n_segments
    labels = trial.labels
    first_group = [lab for lab, s in zip(labels, prep.segmentation.marker_segment) if s == 0][:2]
    calls, moved = [], []

    def first(p):
        assert not moved  # the motion waits for the kept fit
        warnings.warn("from the first fit", _Note)
        return _result(p, p.segmentation, first_group)

    def refit(p):
        calls.append(p.segmentation.n_segments)
        warnings.warn(f"from the refit with {p.segmentation.n_segments}", _Note)
        return _result(p, p.segmentation, ())

    def add_motion(p, r):
        moved.append(r.segmentation.n_segments)
        return dataclasses.replace(r, motion="moved")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = _grow(prep, first, refit, add_motion, stacklevel=3)  # _grow, then this test
    assert calls == [m0 + 1]
    seg = out.segmentation
    assert (seg.count_rule, seg.split_from, seg.n_segments) == ("split", m0, m0 + 1)
    assert seg.split_markers == tuple(sorted(first_group, key=labels.index))
    assert seg.eigengap_segments == prep.segmentation.eigengap_segments
    assert out.motion == "moved" and moved == [m0 + 1]  # the motion of the kept fit only
    # only the kept fit's warnings reach the user, pointing at the caller's line
    assert [str(w.message) for w in caught] == [f"from the refit with {m0 + 1}"]
    assert caught[0].filename == __file__
    assert "split" in prep.timings


@pytest.mark.usefixtures("skeleton_reading_only")
def test_a_split_that_does_not_remove_flags_is_discarded(trial):
    prep = _prep(trial)
    group = [lab for lab, s in zip(trial.labels, prep.segmentation.marker_segment) if s == 0][:2]

    def first(p):
        warnings.warn("kept", _Note)
        return _result(p, p.segmentation, group)

    def refit(p):  # as many flags as before: not better
        warnings.warn("discarded", _Note)
        return _result(p, p.segmentation, group)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = _grow(prep, first, refit)
    assert out.segmentation is prep.segmentation
    assert [str(w.message) for w in caught] == ["kept"]


def test_a_given_count_never_grows_and_growth_is_bounded(trial):
    labels = trial.labels
    calls = []

    def flagging(n_flags):
        """A stub fit whose skeleton holds every marker on one segment and flags ``n_flags``."""
        def fit(p):
            calls.append(p.segmentation.n_segments)
            r = _result(p, p.segmentation, labels[:n_flags])
            r.skeleton.marker_segment = np.zeros(len(labels), dtype=int)
            return r
        return fit

    given = _prep(trial, n_segments=11)
    out = _grow(given, flagging(4), flagging(0), n_segments=11)
    assert calls == [11] and out.segmentation.count_rule == "given"

    # every split removes a flag but leaves two or more on one segment: MAX_SPLITS refits.
    # The paper's clustering (no mend): mended, the 13 groups of this 12-segment body
    # leave a marker alone (the mend returns a split segment's marker to its mates), and
    # the singleton rule, tested below, would discard that split.
    calls.clear()
    counts = iter(range(2 + MAX_SPLITS + 3, 0, -1))
    out = _grow(_prep(trial), flagging(next(counts)), lambda p: flagging(next(counts))(p), mend=False)
    assert calls == [11 + k for k in range(MAX_SPLITS + 1)]
    assert out.segmentation.n_segments == 11 + MAX_SPLITS and out.segmentation.split_from == 11


def test_a_split_that_leaves_a_marker_alone_is_discarded():
    """Three markers per rod: a fourth segment takes a marker alone (always "rigid", its
    joint often untestable), so the split is not kept even though it flags nothing."""
    trial, _ = synth.simulate(synth.linkage(), duration=8.0, seed=2, noise=0.001)
    prep = _prep(trial)
    assert prep.segmentation.n_segments == 3
    group = [lab for lab, s in zip(trial.labels, prep.segmentation.marker_segment) if s == 0][:2]
    grown = []

    def refit(p):
        grown.append(p.segmentation)
        return _result(p, p.segmentation, ())

    reported = []
    plan = _Plan(FitOptions(), first=lambda p: _result(p, p.segmentation, group), again=refit,
                 on_stage=reported.append, on_more=lambda names: reported.append(names))
    out = plan.grow_count(prep)
    # 4 and 5 groups of 9 markers: each leaves a marker alone, neither is kept
    assert [g.n_segments for g in grown] == [3 + k for k in range(1, MAX_SPLITS + 1)]
    assert all(1 in np.bincount(g.marker_segment) for g in grown)
    assert out.segmentation is prep.segmentation
    # each split is announced (a progress bar's total grows) before it runs, and its refit
    # after it, once a refit is to run; the stub refit reports no stages, the motion stub
    # none either
    assert reported == [("split",), "split", StagePlan.refit_stages] * MAX_SPLITS


def test_a_fit_reports_the_stages_its_plan_lists_and_a_refit_those_a_grown_count_announces():
    """What a progress bar counts: a whole fit reports its plan's `stages` (no "ik" with
    ik=False: before, it reported one stage more than it listed, and a bar ran past its
    total), a refit `refit_stages`."""
    trial, _ = synth.simulate(synth.linkage(), duration=4.0, seed=0, noise=0.001)
    for settings in ({"ik": False}, {"rigid": False}):
        reported = []
        plan = StagePlan(FitOptions.from_settings(**settings), on_stage=reported.append)
        plan.fit(trial)
        assert tuple(reported) == plan.stages, settings
    reported = []
    StagePlan(FitOptions(), on_stage=reported.append).refit(_prep(trial))
    assert tuple(reported) == StagePlan.refit_stages
    # a passive recording: the label merges are checked against the skeleton, a stage the
    # plan announces before it runs (a bar ran past its total there too)
    passive, _ = synth.simulate(synth.linkage(), duration=15.0, seed=2, noise=0.001, gaps=2, relabel=True)
    reported, announced = [], []
    plan = StagePlan(FitOptions.from_settings(merge_labels=True), on_stage=reported.append,
                     on_more=announced.append)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan.fit(passive)
    assert "confirm merges" in reported and ("confirm merges",) in announced
    assert len(reported) == len(plan.stages) + sum(len(names) for names in announced)
    assert sorted(reported) == sorted([*plan.stages, *(name for names in announced for name in names)])


def test_a_count_not_kept_does_not_end_the_search(trial):
    """One more segment flags as many markers as before (not kept); the count after it
    flags fewer and is kept: the counts tried are counted from the last one tried."""
    prep = _prep(trial)
    m0 = prep.segmentation.n_segments
    group = [lab for lab, s in zip(trial.labels, prep.segmentation.marker_segment) if s == 0][:2]
    calls = []

    def refit(p):
        calls.append(p.segmentation.n_segments)
        warnings.warn(f"refit {p.segmentation.n_segments}", _Note)
        return _result(p, p.segmentation, group if len(calls) == 1 else ())

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # mended, 13 groups leave a marker alone (test above)
        out = _grow(prep, lambda p: _result(p, p.segmentation, group), refit, mend=False)
    assert calls == [m0 + 1, m0 + 2]
    seg = out.segmentation
    assert (seg.count_rule, seg.split_from, seg.n_segments) == ("split", m0, m0 + 2)
    assert [str(w.message) for w in caught] == [f"refit {m0 + 2}"]


def test_the_groups_scatter_splits_a_joined_pair_that_the_rigid_skeleton_does_not_flag(trial):
    """The eigengap joins segments 9 and 10 of this tree; the stub skeletons flag nothing,
    so only the groups' scatter can start the split: one more segment mends its flags, and
    that count is fitted and kept, with the true groups."""
    from helpers import partition

    _, truth = synth.simulate(synth.random_tree(12, seed=3), duration=20.0, seed=3, noise=0.001, gaps=2)
    prep = _prep(trial)
    m0 = prep.segmentation.n_segments
    calls = []

    def refit(p):
        calls.append(p.segmentation.n_segments)
        return _result(p, p.segmentation, ())

    out = _grow(prep, lambda p: _result(p, p.segmentation, ()), refit)
    assert calls == [m0 + 1]
    seg = out.segmentation
    assert (seg.count_rule, seg.split_from, seg.n_segments) == ("split", m0, m0 + 1)
    assert len(seg.split_markers) >= 2 and all(lab.startswith(("S9M", "S10M")) for lab in seg.split_markers)
    assert partition(trial.labels, seg.marker_segment) == partition(trial.labels, truth.marker_segment)


def test_scatter_flags_that_no_count_mends_are_not_fitted(trial, monkeypatch):
    """Soft tissue flags a whole group that no count mends: the grown segmentations are
    read, none is fitted. Where the rigid skeleton flags the group too, each count is
    fitted and judged by the skeleton's flags, as without the scatter."""
    prep = _prep(trial)
    m0 = prep.segmentation.n_segments
    group = [lab for lab, s in zip(trial.labels, prep.segmentation.marker_segment) if s == 0][:2]
    monkeypatch.setattr(_plan, "read_scatter", lambda trial, segmentation: ScatterReading(tuple(group), len(group)))
    judged = []
    monkeypatch.setattr(_plan, "scatter_splits", lambda *args: judged.append(args[2].n_segments) or False)
    calls = []

    def refit(p):
        calls.append(p.segmentation.n_segments)
        return _result(p, p.segmentation, ())

    out = _grow(prep, lambda p: _result(p, p.segmentation, ()), refit, mend=False)
    assert judged == [m0 + k for k in range(1, MAX_SPLITS + 1)] and calls == []
    assert out.segmentation is prep.segmentation and "split" in prep.timings
    # a progress bar counts only what runs: each split's segmentation, no refit
    reported = []
    plan = _Plan(FitOptions.from_settings(mend=False), first=lambda p: _result(p, p.segmentation, ()), again=refit,
                 on_stage=reported.append, on_more=reported.append)
    plan.grow_count(_prep(trial))
    assert reported == [("split",), "split"] * MAX_SPLITS and calls == []

    judged.clear()
    out = _grow(_prep(trial), lambda p: _result(p, p.segmentation, group), refit, mend=False)
    # m0 + 1: the skeleton's flags drop, kept; m0 + 2: only the (stub) scatter still flags, read and not fitted
    assert judged == [m0 + 1, m0 + 2] and calls == [m0 + 1]
    assert out.segmentation.n_segments == m0 + 1 and out.segmentation.split_markers == tuple(group)
