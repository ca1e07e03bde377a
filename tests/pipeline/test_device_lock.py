"""The batch pipeline's device lock (jaxskel.pipeline._local.DEVICE_LOCK): every JAX stage of
a batch, from any of its threads, runs under it. A unit test of the pipeline's internals;
the end-to-end batch tests are in tests/test_batch.py."""

import jaxskel
from jaxskel import synth


def test_every_jax_stage_of_a_batch_runs_under_the_device_lock(monkeypatch, tmp_path):
    """The batch deadlock (issue 49): the pose check's segment poses ran in the main thread
    outside the device lock while a finishing thread ran the anchored refit's, and two
    XLA:CPU executions at once hang for good. Every call of the segment poses, from any
    of the batch's threads, must hold the lock (checked, not timed: a hang is a race)."""
    from jaxskel.joints import _anchored_centres
    from jaxskel.pipeline import _local

    calls: list[tuple[str, bool]] = []  # every JAX call of the segment poses goes through these

    def guarded(real):
        def call(*args, **kwargs):
            calls.append((__import__("threading").current_thread().name, _local.DEVICE_LOCK._is_owned()))
            return real(*args, **kwargs)

        return call

    # Kept: an instrument (it records whether the lock is held and calls through), the only
    # way to check a race by ownership instead of by timing. The mean clouds and the two
    # alignment passes are all the device work of the pose check's and the anchored refit's
    # segment poses.
    for name in ("_mean_clouds", "_pose_frames", "_pose_rows"):
        monkeypatch.setattr(_anchored_centres, name, guarded(getattr(_anchored_centres, name)))
    body = synth.full_body()
    trials = [synth.simulate(body, duration=4.0, seed=70 + i, noise=0.001)[0] for i in range(4)]
    result = jaxskel.fit_batch(trials, tmp_path, batch_size=2, jobs=2, n_segments=len(body.segment_names))
    assert [o.status for o in result] == ["ok"] * 4
    threads = {name.split("_")[0] for name, _ in calls}
    assert "MainThread" in threads and any(t.startswith("jaxskel-finish") for t in threads), threads
    assert all(owned for _, owned in calls), [c for c in calls if not c[1]]
