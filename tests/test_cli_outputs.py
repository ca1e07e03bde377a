"""Issue 45, items 2 and 9 (preflight): every output of `jaxskel fit` and `jaxskel fit-batch`
is checked before any input is read or any fit starts: a known file type, not a folder
(and for fit-batch a folder, not a file), a writable place, no input and no other output.
The fits are replaced by stubs that fail the test if they are reached (before, these
outputs failed only after the whole fit, some with a traceback)."""

import os
import stat

import numpy as np
import pytest

import jaxskel
from jaxskel.cli import main

IMAGE_TYPES = ".avif, .eps, .gif, .jpeg, .jpg, .pdf, .pgf, .png, .ps, .raw, .rgba, .svg, .svgz, .tif, .tiff, .webp"


@pytest.fixture
def no_work(monkeypatch):
    """Reading a recording or fitting fails the test: the command must stop before."""

    def started(*args, **kwargs):
        raise AssertionError("the work started before the outputs were checked")

    for name in ("load", "fit_skeleton", "fit_batch"):
        monkeypatch.setattr(jaxskel, name, started)


@pytest.fixture
def recording(tmp_path):
    trial = jaxskel.Trial(np.random.default_rng(0).normal(size=(20, 3, 3)), ["a", "b", "c"], 100.0)
    return jaxskel.save_trial(trial, tmp_path / "walk.trc")


def unwritable(monkeypatch, folder):
    """``folder`` as a user without write permission sees it (root writes anywhere)."""
    folder.chmod(stat.S_IRUSR | stat.S_IXUSR)
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if os.path.samefile(p, folder) else real(p, mode))


def error(capsys):
    err = capsys.readouterr().err
    assert err.startswith("jaxskel: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    return err[len("jaxskel: error: "):-1]


def test_fit_refuses_an_output_it_cannot_write_before_any_work(recording, tmp_path, monkeypatch, capsys, no_work):
    src, d = str(recording), tmp_path
    cases = {
        ("-o", "r.txt"): f"-o {d}/r.txt: a result file must end in .h5 or .hdf5, not '.txt' (e.g. {d}/r.h5)",
        ("--plot", "p.xyz"): f"--plot {d}/p.xyz: matplotlib cannot write a '.xyz' image; give a name ending in one of "
        f"{IMAGE_TYPES} (e.g. {d}/p.png)",
        ("--plot", "summary"): f"--plot {d}/summary: matplotlib cannot write an image without a file type; give a name "
        f"ending in one of {IMAGE_TYPES} (e.g. {d}/summary.png)",
        ("--bvh", "s.txt"): f"--bvh {d}/s.txt: a BVH file must end in .bvh, not '.txt' (e.g. {d}/s.bvh)",
        ("--trc", "m.csv"): f"--trc {d}/m.csv: a TRC file must end in .trc, not '.csv' (e.g. {d}/m.trc)",
        ("--osim", "m.xml"): f"--osim {d}/m.xml: an OpenSim model must end in .osim, not '.xml' (e.g. {d}/m.osim)",
        ("--bvh", "walk.trc/s.bvh"): f"--bvh {d}/walk.trc/s.bvh: {d}/walk.trc is a file, not a folder",
    }
    for (flag, name), text in cases.items():
        args = ["fit", src, "-o", str(d / "r.h5"), "--quiet"]
        if flag == "-o":
            args[3] = str(d / name)
        else:
            args += [flag, str(d / name)]
        assert main(args) == 2
        assert error(capsys) == text
    assert sorted(p.name for p in d.iterdir()) == ["walk.trc"]  # nothing written


def test_fit_o_naming_a_folder_says_to_give_a_file_inside_it(recording, tmp_path, capsys, no_work):
    """Issue 45, item 9."""
    folder = tmp_path / "results"
    folder.mkdir()
    assert main(["fit", str(recording), "-o", str(folder), "--quiet"]) == 2
    assert error(capsys) == f"-o {folder}: it is a folder; give a file name inside it, e.g. {folder}/result.h5"
    assert main(["fit", str(recording), "-o", str(tmp_path / "r.h5"), "--plot", str(folder), "--quiet"]) == 2
    assert error(capsys) == f"--plot {folder}: it is a folder; give a file name inside it, e.g. {folder}/summary.png"


def test_fit_refuses_an_unwritable_folder_before_any_work(recording, tmp_path, monkeypatch, capsys, no_work):
    locked = tmp_path / "locked"
    locked.mkdir()
    unwritable(monkeypatch, locked)
    try:
        for flag in ("-o", "--trc", "--plot"):
            name = {"-o": "r.h5", "--trc": "m.trc", "--plot": "p.png"}[flag]
            args = ["fit", str(recording), "-o", str(tmp_path / "r.h5"), "--quiet"]
            if flag == "-o":
                args[3] = str(locked / name)
            else:
                args += [flag, str(locked / "sub" / name)]  # a folder to create under it: the same
            assert main(args) == 2
            where = locked / name if flag == "-o" else locked / "sub" / name
            assert error(capsys) == f"{flag} {where}: the folder {locked} is not writable; choose another place"
    finally:
        locked.chmod(stat.S_IRWXU)


@pytest.fixture
def folder_of_recordings(tmp_path):
    src = tmp_path / "in"
    (src / "s1").mkdir(parents=True)
    trial = jaxskel.Trial(np.random.default_rng(0).normal(size=(20, 3, 3)), ["a", "b", "c"], 100.0)
    jaxskel.save_trial(trial, src / "s1" / "t1.c3d")
    jaxskel.save_trial(trial, src / "t2.trc")
    return src


def test_fit_batch_refuses_its_outputs_before_any_work(folder_of_recordings, tmp_path, monkeypatch, capsys, no_work):
    src = folder_of_recordings
    folder = "fit-batch writes a folder (one result file per recording, and summary.csv)"
    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a folder")
    out = tmp_path / "out"

    def run(*args):
        assert main(["fit-batch", str(src), *args, "--quiet"]) == 2
        return error(capsys)

    # Issue 45, item 9 the other way round: fit-batch wants a folder
    assert run("-o", str(a_file)) == f"-o {a_file} is a file, but {folder}: give a folder name, e.g. -o {tmp_path}/notes"
    assert run("-o", str(tmp_path / "res.h5")) == (
        f"-o {tmp_path}/res.h5 is a file name, but {folder}: give a folder name, e.g. -o {tmp_path}/res"
    )
    tail = "and fit-batch leaves out every file under its output folder when it looks for recordings: give another " \
        f"output folder, e.g. -o {src}/results"
    assert run("-o", str(src)) == f"-o {src} is the input folder {src}, {tail}"
    assert run("-o", str(tmp_path)) == f"-o {tmp_path} holds the input folder {src}, {tail}"
    bones = ["--bone", "x=a,b,c", "--bone", "y=a,b,c"]
    assert run("-o", str(out), *bones, "--plot-bones", str(tmp_path / "b.xyz")) == (
        f"--plot-bones {tmp_path}/b.xyz: matplotlib cannot write a '.xyz' image; give a name ending in one of "
        f"{IMAGE_TYPES} (e.g. {tmp_path}/b.png)"
    )
    assert run("-o", str(out), *bones, "--plot-bones", str(src / "t2.trc"), "--overwrite") == (
        f"--plot-bones {src}/t2.trc is the input recording {src}/t2.trc; jaxskel never writes over an input, even "
        "with overwrite: choose another name"
    )
    assert run("-o", str(out), *bones, "--plot-bones", str(out / "summary.csv")) == (
        f"--plot-bones {out}/summary.csv is the summary table; give the plot its own file"
    )
    (out / "summary.csv").mkdir(parents=True)
    assert run("-o", str(out)) == (
        f"the summary table {out}/summary.csv is a folder; move it away or give another output folder"
    )
    (out / "summary.csv").rmdir()
    (out / "t2.h5").mkdir()
    assert run("-o", str(out)) == (
        f"the result file of t2, {out}/t2.h5, is a folder; move it away or give another output folder"
    )
    (out / "t2.h5").rmdir()
    unwritable(monkeypatch, out)
    try:
        assert run("-o", str(out)) == f"-o {out}: the folder {out} is not writable; choose another place"
        assert run("-o", str(out / "new")) == f"-o {out}/new: the folder {out} is not writable; choose another place"
    finally:
        out.chmod(stat.S_IRWXU)
    assert sorted(p.name for p in out.iterdir()) == []  # nothing written


def test_the_library_refuses_an_unknown_file_type_before_it_writes(tmp_path):
    """The API's writers check the path before they touch the result (a stand-in that any
    use would break) or draw anything."""
    for write, text in (
        (lambda p: jaxskel.SkeletonResult.save(None, p), "a result file must end in .h5 or .hdf5, not '.txt'"),
        (lambda p: jaxskel.result.export_bvh(None, None, p), "a BVH file must end in .bvh, not '.txt'"),
        (lambda p: jaxskel.plots.plot_summary(None, p), "matplotlib cannot write a '.txt' image"),
        (lambda p: jaxskel.pipeline.plot_bone_lengths([], "x", "y", path=p), "matplotlib cannot write a '.txt' image"),
    ):
        with pytest.raises(jaxskel.InputError, match=f"^cannot write {tmp_path}/out.txt: {text}"):
            write(tmp_path / "out.txt")
    with pytest.raises(jaxskel.InputError, match=f"^cannot write {tmp_path}: it is a folder; give a file name "
                       f"inside it, e.g. {tmp_path}/skeleton.bvh$"):
        jaxskel.result.export_bvh(None, None, tmp_path)
    assert list(tmp_path.iterdir()) == []
