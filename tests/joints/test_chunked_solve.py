"""The chunked batched solve of the joint stages: a pair's answer does not depend on its
chunk mates or the chunk size, and a subsample of exactly ``max_frames`` frames is not padded."""

import numpy as np
import pytest

from jaxskel.joints._topology import solve_chunked

from test_jointcost import chain

pytestmark = pytest.mark.usefixtures("float64")


def _pairs():
    """Four pairs of 6 markers, 120 frames: ball, hinge, static and a wrong pairing (no joint)."""
    xs = []
    for kind, seed in (("ball", 0), ("hinge", 1), ("static", 2)):
        markers, _ = chain(kind, frames=120, seed=seed)
        xs.append(np.concatenate([markers["parent"], markers["child"]], axis=1))
    markers, _ = chain("ball", frames=120, seed=3)
    xs.append(np.concatenate([markers["parent"], markers["grand"]], axis=1))
    xs = np.stack(xs)
    ms = np.ones(xs.shape[:3], bool)
    ms[1, 10:30, 2] = False  # a gap
    return xs, ms


def test_each_pair_gets_the_answer_it_gets_alone():
    xs, ms = _pairs()
    alpha = np.full(len(xs), 1e-5)
    kw = dict(method="lm", max_steps=100)
    together = solve_chunked(xs, ms, alpha, chunk=3, **kw)  # chunks (0, 1, 2) and (3, pad, pad)
    reordered = solve_chunked(xs[::-1], ms[::-1], alpha, chunk=2, **kw)
    for p in range(len(xs)):
        alone = solve_chunked(xs[p:p + 1], ms[p:p + 1], alpha[:1], chunk=1, **kw)
        for name in ("cost", "steps", "result", "positions", "radii"):
            np.testing.assert_allclose(together[name][p], alone[name][0], rtol=1e-9, atol=1e-12, err_msg=name)
            np.testing.assert_allclose(reordered[name][len(xs) - 1 - p], alone[name][0], rtol=1e-9, atol=1e-12,
                                       err_msg=name)
    # the pairs differ in how long they take: a chunk's slowest pair does not set the others' steps
    assert len(set(together["steps"].tolist())) > 1


@pytest.mark.parametrize("max_frames, count", [(300, 300), (500, 400)])
def test_a_subsample_of_exactly_max_frames_is_not_padded(max_frames, count):
    """1200 frames: max_frames 300 takes every 4th frame, exactly 300 (no padding); 500 takes
    every 3rd, 400 frames, which are padded to their bucket."""
    from jaxskel import synth
    from jaxskel._math.padding import bucket_size
    from jaxskel.joints._topology import all_pairs_problem
    from jaxskel.segment import segment_markers

    trial, _ = synth.simulate(synth.linkage(), duration=10.0, seed=0, noise=0.001)
    assert trial.n_frames == 1200
    problem = all_pairs_problem(trial, segment_markers(trial), max_frames=max_frames)
    assert len(problem.frames) == count
    assert problem.xs.shape[1] == (count if count == max_frames else bucket_size(count))
    assert problem.ms[:, count:].sum() == 0 and problem.ms[:, :count].any(axis=(0, 2)).all()
