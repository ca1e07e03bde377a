"""fit_batch and `jaxskel fit-batch`: equal to per-trial fits, resumable, failures reported,
summary table, bone plot, Dask local cluster, several devices."""

import csv
import json
import os
import shutil
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest

import jaxskel
from jaxskel import synth
from jaxskel.cli import main

BONES = {"middle": ("R1M1", "R2M1", "R3M1")}


@pytest.fixture(scope="module")
def trials():
    return [
        synth.simulate(synth.linkage(), duration=6.0 + i, seed=21 + i, noise=0.001)[0] for i in range(3)
    ]


@pytest.fixture(scope="module")
def batch(trials, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch")
    bad = jaxskel.Trial(positions=trials[0].positions[:, :2], labels=trials[0].labels[:2], rate=120.0)
    items = [*trials, bad, out / "missing.c3d"]
    result = jaxskel.fit_batch(
        items, out, names=["a", "b", "c", "bad", "missing"], subjects=["s1", "s1", "s2", "s2", "s2"],
        bones=BONES, keep_results=True,
    )
    return out, result


def read_csv(path):
    with open(path, newline="") as f:
        return {row["name"]: row for row in csv.DictReader(f)}


def test_batch_equals_fit_skeleton(batch, trials):
    _, result = batch
    assert [o.status for o in result] == ["ok", "ok", "ok", "failed", "failed"]
    for outcome, trial in zip(result, trials):
        alone = jaxskel.fit_skeleton(trial)
        got = outcome.result
        np.testing.assert_array_equal(got.edges, alone.edges)
        np.testing.assert_allclose(got.joint_positions, alone.joint_positions, rtol=0, atol=1e-9, equal_nan=True)
        np.testing.assert_allclose(got.topology.pair_costs.cost, alone.topology.pair_costs.cost, rtol=1e-9)
        np.testing.assert_allclose(got.skeleton.bone_lengths, alone.skeleton.bone_lengths, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.motion.marker_rms, alone.motion.marker_rms, rtol=0, atol=1e-9)
        back = outcome.load()  # the file holds the same
        np.testing.assert_allclose(back.joints.positions, alone.joint_positions, atol=1e-9, equal_nan=True)


def test_failures_are_rows_not_exceptions(batch):
    out, result = batch
    bad, missing = result[3], result[4]
    assert bad.status == "failed" and "DegenerateMotionError" in bad.error and "markers" in bad.error
    assert missing.status == "failed" and "missing.c3d" in missing.error
    assert not (out / "bad.h5").exists() and not (out / "missing.h5").exists()
    assert len(result.failed) == 2 and result.counts() == {"ok": 3, "failed": 2}


def test_summary_csv(batch, trials):
    out, result = batch
    rows = read_csv(out / "summary.csv")
    assert list(rows) == ["a", "b", "c", "bad", "missing"]
    a = rows["a"]
    assert a["status"] == "ok" and a["subject"] == "s1" and a["output"].endswith("a.h5")
    assert int(a["frames"]) == trials[0].n_frames and int(a["segments"]) == 3 and a["joints_converged"] == "2/2"
    assert a["undetermined"] == "0"  # the linkage's calibration motion fixes both joints
    assert abs(float(a["bone:middle"]) - 0.341) < 0.003  # the linkage's middle rod is 0.341 m
    assert json.loads(a["bones"]) == {"R2M1:R1M1-R3M1": pytest.approx(float(a["bone:middle"]), abs=1e-6)}
    assert float(a["ik_rms_median_mm"]) < 3.0 and float(a["seconds"]) > 0
    assert rows["bad"]["status"] == "failed" and rows["bad"]["error"] and rows["bad"]["output"] == ""
    assert result.table()[0]["name"] == "a"


def test_rerun_skips_finished_and_redoes_partial_outputs(batch, trials, tmp_path):
    src, _ = batch
    out = tmp_path / "copy"
    shutil.copytree(src, out)
    again = jaxskel.fit_batch(trials, out, names=["a", "b", "c"], bones=BONES)
    assert [o.status for o in again] == ["skipped"] * 3
    assert again[0].row["bone:middle"] == pytest.approx(float(read_csv(src / "summary.csv")["a"]["bone:middle"]))
    # a truncated file and a result without a completion record do not count as finished
    data = (out / "b.h5").read_bytes()
    (out / "b.h5").write_bytes(data[: len(data) // 2])
    with h5py.File(out / "c.h5", "a") as f:
        del f["batch"]
    redo = jaxskel.fit_batch(trials, out, names=["a", "b", "c"], bones=BONES)
    assert [o.status for o in redo] == ["skipped", "ok", "ok"]
    assert jaxskel.load_result(out / "b.h5").batch.attrs["complete"]
    # other settings are another job: nothing is skipped
    assert [o.status for o in jaxskel.fit_batch(trials[:1], out, names=["a"], rigid=False)] == ["ok"]
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]  # no partial files left behind


def test_plot_bone_lengths(batch, tmp_path):
    out, result = batch
    fig = tmp_path / "bones.png"
    ax = jaxskel.pipeline.plot_bone_lengths(out / "summary.csv", "middle", "bone:middle", path=fig)
    assert fig.stat().st_size > 5_000 and len(ax.collections) == 2  # subjects s1 and s2
    with pytest.raises(jaxskel.InputError, match="no column"):
        jaxskel.pipeline.plot_bone_lengths(result, "back", "middle")


def test_bone_length_by_marker_labels(batch):
    _, result = batch
    r = result[0].result
    assert jaxskel.pipeline.bone_length(r, ("R1M1", "R2M2", "R3M3")) == pytest.approx(r.skeleton.bone_lengths[0])
    assert np.isnan(jaxskel.pipeline.bone_length(r, ("R1M1", "R1M2", "R3M3")))  # rod1 is a leaf: no bone
    assert np.isnan(jaxskel.pipeline.bone_length(r, ("nope", "R2M2", "R3M3")))
    with pytest.raises(jaxskel.InputError, match="triple"):
        jaxskel.pipeline.bone_length(r, ("R1M1", "R2M2"))


def test_cli_fit_batch_local_and_errors(trials, tmp_path, capsys):
    src = tmp_path / "in"
    (src / "subjA").mkdir(parents=True)
    trials[0].save(src / "subjA" / "t0.c3d")
    trials[1].save(src / "t1.trc")
    out = tmp_path / "out"
    assert main(["fit-batch", str(src), "-o", str(out), "--quiet", "--no-rigid"]) == 0
    rows = read_csv(out / "summary.csv")
    assert set(rows) == {"subjA/t0", "t1"} and rows["subjA/t0"]["subject"] == "subjA"
    assert (out / "subjA" / "t0.h5").is_file()
    # the paper's tree on request: the setting reaches every fit (and its completion record)
    plain = tmp_path / "plain"
    assert main(["fit-batch", str(src), "-o", str(plain), "--quiet", "--no-rigid", "--no-pose-check"]) == 0
    for folder, checked in ((out, True), (plain, False)):
        with h5py.File(folder / "subjA" / "t0.h5") as f:
            assert json.loads(f["diagnostics"].attrs["settings"])["pose_check"] is checked
    assert main(["fit-batch", str(tmp_path / "nowhere"), "-o", str(out), "--quiet"]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main(["fit-batch", str(src), "-o", str(out), "--quiet", "--bone", "x=a,b"]) == 2
    # a memory bound that is not a size is refused before any work
    assert main(["fit-batch", str(src), "-o", str(tmp_path / "m"), "--quiet", "--memory", "lots"]) == 2
    assert "is not a size" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_cli_fit_batch_on_a_local_dask_cluster(trials, tmp_path):
    distributed = pytest.importorskip("distributed")
    src = tmp_path / "in"
    for i, trial in enumerate(trials[:2] * 2):
        folder = src / f"subj{i % 2}"
        folder.mkdir(parents=True, exist_ok=True)
        trial.save(folder / f"t{i}.c3d")
    (src / "broken.c3d").write_bytes(b"not a c3d file")
    out, fig = tmp_path / "out", tmp_path / "bones.png"
    args = ["fit-batch", str(src), "-o", str(out), "--quiet", "--no-rigid", "--bone", "middle=R1M1,R2M1,R3M1",
            "--bone", "mid2=R3M3,R2M3,R1M3", "--plot-bones", str(fig)]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        assert len(cluster.workers) == 2
        assert main([*args, "--scheduler", cluster.scheduler_address]) == 1  # broken.c3d failed
        rows = read_csv(out / "summary.csv")
        assert rows["broken"]["status"] == "failed" and "C3D" in rows["broken"]["error"]
        ok = [r for r in rows.values() if r["status"] == "ok"]
        assert len(ok) == 4 and {r["subject"] for r in ok} == {"subj0", "subj1"}
        assert all(abs(float(r["bone:middle"]) - 0.341) < 0.005 for r in ok)
        assert fig.stat().st_size > 5_000
        # rerun on the cluster: everything finished is skipped
        assert main([*args[:8], "--scheduler", cluster.scheduler_address]) == 1
        rows = read_csv(out / "summary.csv")
        assert sorted(r["status"] for r in rows.values()) == ["failed"] + ["skipped"] * 4


@pytest.mark.extended  # about a minute on 2 cores; CI runs the rest
def test_chunks_are_spread_over_several_devices(tmp_path):
    script = textwrap.dedent(
        """
        import jax, numpy as np, jaxskel
        from jaxskel import synth
        assert jax.device_count() == 2, jax.devices()
        trials = [synth.simulate(synth.linkage(), duration=4.0, seed=s, noise=0.001)[0] for s in (1, 2, 3)]
        used = set()
        put = jax.device_put
        def spy(x, device=None, *a, **k):
            if device is not None:
                used.add(device.id)
            return put(x, device, *a, **k)
        jax.device_put = spy
        two = jaxskel.fit_batch(trials, rigid=False, devices="auto")
        jax.device_put = put
        one = jaxskel.fit_batch(trials, rigid=False, devices="default")
        assert used == {0, 1}, used
        for a, b in zip(two, one):
            assert a.status == b.status == "ok", (a.error, b.error)
            np.testing.assert_allclose(a.result.joint_positions, b.result.joint_positions, atol=1e-9, equal_nan=True)
        print("SHARDED OK")
        """
    )
    # two forced host devices, with the run's single-threaded Eigen kept (conftest.py; jaxskel's import no longer adds it)
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env = dict(os.environ, XLA_FLAGS=flags)
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900)
    assert "SHARDED OK" in proc.stdout, proc.stderr[-3000:]


def test_programs_are_dropped_near_the_mapping_limit_and_the_batch_is_unchanged(batch, trials, monkeypatch):
    """Past three quarters of vm.max_map_count (XLA segfaults past the limit itself),
    fit_batch drops JAX's compiled programs before it solves the next batch, says so once,
    and the trial's fit is what it was with the programs kept."""
    from jaxskel._runtime import map_limit as _map_limit
    # Kept: a process near vm.max_map_count, simulated (short of exhausting the mappings,
    # the only way there), and the per-process "said once" flag reset for this test.
    monkeypatch.setattr(_map_limit, "RELEASE_FRACTION", 0.0)  # every count is near the limit
    monkeypatch.setitem(_map_limit._state, "warned", False)
    with pytest.warns(RuntimeWarning, match="vm.max_map_count") as caught:
        (again,) = jaxskel.fit_batch(trials[:1], names=["a"], rigid=False, ik=False, keep_results=True)
    assert sum("vm.max_map_count" in str(w.message) for w in caught) == 1
    _, result = batch
    np.testing.assert_array_equal(again.result.edges, result[0].result.edges)
    np.testing.assert_allclose(again.result.topology.pair_costs.cost, result[0].result.topology.pair_costs.cost,
                               rtol=1e-9)


def test_a_batch_that_overlaps_preparing_solving_and_finishing_finishes(tmp_path):
    """End to end in a fresh process, with a timeout that turns a hang into a failure:
    six full bodies in batches of two, two threads per pool, so that preparing trial k+2,
    solving k+1 and finishing k overlap."""
    script = textwrap.dedent(f"""
        import jaxskel
        from jaxskel import synth
        body = synth.full_body()
        trials = [synth.simulate(body, duration=4.0, seed=80 + i, noise=0.002)[0] for i in range(6)]
        result = jaxskel.fit_batch(trials, {str(tmp_path)!r}, batch_size=2, jobs=2,
                                   n_segments=len(body.segment_names))
        print("statuses", [o.status for o in result])
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "statuses ['ok', 'ok', 'ok', 'ok', 'ok', 'ok']" in proc.stdout, proc.stdout


def test_a_batch_over_its_memory_bound_is_split_and_fits_the_same(batch, trials, monkeypatch, capsys):
    """``memory`` bounds the trials solved together by their estimated peak (14 times the
    positions): with room for the largest trial but not for two, each is solved alone;
    with room for all, the three go together. The fits do not change. The progress bar
    counts trials and estimates the time left."""
    import re

    from jaxskel.pipeline import _local
    from jaxskel.pipeline._batch_memory import fit_bytes

    sizes = []
    solve = _local._solve_batch

    def spy(works, *args, **kwargs):
        sizes.append(len(works))
        return solve(works, *args, **kwargs)

    monkeypatch.setattr(_local, "_solve_batch", spy)
    largest = max(fit_bytes(t.n_frames, t.n_markers) for t in trials)
    split = jaxskel.fit_batch(trials, memory=int(1.2 * largest), progress=True)
    assert sizes == [1, 1, 1]
    bar = capsys.readouterr().err
    assert re.search(r"fit_batch: +\d+%.*\| *[12]/3 \[\d\d:\d\d<\d\d:\d\d", bar), bar  # elapsed<left
    sizes.clear()
    together = jaxskel.fit_batch(trials, memory=f"{4 * largest / 2**20:.3f}MB")
    assert sizes == [3]
    for a, b, c in zip(split, together, batch[1]):
        np.testing.assert_array_equal(a.result.edges, c.result.edges)
        np.testing.assert_allclose(a.result.skeleton.bone_lengths, c.result.skeleton.bone_lengths, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.result.skeleton.bone_lengths, c.result.skeleton.bone_lengths, rtol=0, atol=1e-9)
    with pytest.raises(jaxskel.InputError, match="is not a size"):
        jaxskel.fit_batch(trials, memory="a lot")
