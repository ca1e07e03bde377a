"""jaxskel.pipeline._trial_warnings: a batch's warnings caught per trial in threads and said
again naming the trial (the contract of its module docstring)."""

import pickle
import threading
import warnings

import pytest

from jaxskel import DegenerateMotionWarning
from jaxskel.pipeline._trial_warnings import TrialWarnings, emit, pack, unpack


def same_place(text, category=UserWarning):
    warnings.warn(text, category)  # one code location for every trial


def test_each_trial_in_each_thread_gets_its_own_warnings_even_from_one_code_location():
    lock = threading.RLock()
    tw = TrialWarnings(records_under=lock)
    barrier = threading.Barrier(3)

    def work(key):
        with tw.trial(key):
            barrier.wait()
            same_place("the same words")
            same_place("the same words")  # once per trial
            same_place(f"only {key}", DegenerateMotionWarning)

    with warnings.catch_warnings(record=True) as shown:
        warnings.resetwarnings()  # no filter: Python's default action, once per code location
        same_place("the same words")  # the registry of that location has this now
        with tw.installed():
            threads = [threading.Thread(target=work, args=(k,)) for k in "abc"]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            same_place("outside any trial")
    for key in "abc":
        assert tw.take(key) == ((UserWarning, "the same words"), (DegenerateMotionWarning, f"only {key}"))
        assert tw.take(key) == ()
    assert [str(w.message) for w in shown] == ["the same words", "outside any trial"]


def test_a_filter_the_user_set_still_applies():
    tw = TrialWarnings(records_under=threading.RLock())
    with warnings.catch_warnings(), tw.installed(), tw.trial("a"):
        warnings.simplefilter("ignore", DegenerateMotionWarning)
        same_place("ignored", DegenerateMotionWarning)
        same_place("kept")
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(RuntimeWarning, match="raised"):
            same_place("raised", RuntimeWarning)
    assert tw.take("a") == ((UserWarning, "kept"),)


def test_a_record_of_the_lock_holder_keeps_its_warnings_and_other_threads_are_not_recorded():
    """StagePlan.grow_count records the warnings of candidate fits under the device lock and
    says again only the kept one's; a warning of another trial's thread meanwhile stays that
    trial's (before, it went into the record, then to the recording trial)."""
    lock = threading.RLock()
    tw = TrialWarnings(records_under=lock)
    recording, other_done = threading.Event(), threading.Event()

    def recorder():
        with tw.trial("kept"), lock:
            with warnings.catch_warnings(record=True) as caught:
                recording.set()
                same_place("a discarded candidate's warning")
                other_done.wait(10)
            assert [str(w.message) for w in caught] == ["a discarded candidate's warning"]
            same_place("the kept fit's warning")

    def other():
        recording.wait(10)
        with tw.trial("other"):
            same_place("another trial's warning")
        other_done.set()

    with tw.installed():
        threads = [threading.Thread(target=recorder), threading.Thread(target=other)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert tw.take("kept") == ((UserWarning, "the kept fit's warning"),)
    assert tw.take("other") == ((UserWarning, "another trial's warning"),)


def test_emit_names_the_trial_and_the_state_is_restored_afterwards():
    before = (warnings._showwarnmsg, warnings.defaultaction, warnings.showwarning)
    tw = TrialWarnings(records_under=threading.RLock())
    with tw.installed():
        with tw.installed():  # a second batch in the process shares the hook
            pass
        assert warnings.defaultaction == "always"
        stale = warnings.showwarning = lambda *a, **k: None  # as a catch_warnings ending late leaves it
        tw.heal()
        assert warnings.showwarning is not stale and warnings.showwarning is before[2]
        with pytest.warns(DegenerateMotionWarning) as caught:
            emit("S01/walk", [(DegenerateMotionWarning, "joint 3 barely moves")])
    assert (warnings._showwarnmsg, warnings.defaultaction, warnings.showwarning) == before
    (w,) = caught
    assert str(w.message) == "[S01/walk] joint 3 barely moves"
    assert (w.message.trial, w.message.text) == ("S01/walk", "joint 3 barely moves")


def test_warnings_travel_between_processes_as_plain_data():
    caught = ((DegenerateMotionWarning, "a"), (RuntimeWarning, "b"))
    packed = pickle.loads(pickle.dumps(pack(caught)))
    assert packed == [("jaxskel._errors:DegenerateMotionWarning", "a"), ("builtins:RuntimeWarning", "b")]
    assert unpack(packed) == caught
    assert unpack([("nowhere.module:Gone", "c")]) == ((UserWarning, "c"),)
