"""The ``jaxskel`` command line.

    jaxskel demo [-o DIR]                     fit the bundled real recording
    jaxskel fit INPUT... -o OUT.h5 [options]  fit one subject (several trials fit together)
    jaxskel info FILE                         describe a recording or a result file
    jaxskel fit-batch DIR -o OUTDIR [options] fit every recording in a folder (resumable;
                                              --scheduler ADDRESS / --workers N: Dask)
    jaxskel track SKELETON.h5 TRIAL... -o DIR pose new trials on a saved skeleton

Errors the user can fix (bad file, wrong units, degenerate motion) print one
clear line and exit with status 2; nothing the user gave is overwritten
unless ``--overwrite`` is passed.

The command's process is jaxskel's own: :func:`main` sets XLA's single-threaded Eigen
in ``XLA_FLAGS`` before JAX starts (:mod:`jaxskel._runtime.own_process`), which the
library leaves to its users.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import os
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from ._runtime.compile_cache import enable_compile_cache
from ._runtime.own_process import own_process

if TYPE_CHECKING:
    from .pipeline._options import FitOptions, SettingInfo

# The stages' modules (with scikit-learn and scipy: most of a run's first second) are
# imported where a command needs them, after main() has started reading its compiled
# programs ahead (enable_compile_cache, jaxskel._runtime.program_cache.read_ahead).

__all__ = ["main", "run"]


# ------------------------------------------------------------ settings as flags
def _flag(info: SettingInfo, default: Any) -> str:
    """A setting's flag: as declared, else ``--<flat-name>`` (``--no-...`` for a switch on by default)."""
    if info.flag:
        return info.flag
    name = info.flat.replace("_", "-")
    return f"--no-{name}" if default is True else f"--{name}"


def _value_type(info: SettingInfo) -> Callable[[str], Any]:
    """The argparse ``type`` of a non-switch setting: ``none``/``auto`` where allowed, else a number or text
    (the options object validates the value)."""
    words = dict(info.cli_values or {})

    def parse(text: str) -> Any:
        low = text.lower()
        if low in words:
            return words[low]
        if low == "none" and info.constraint.accepts(None):
            return None
        if low == "auto" and info.constraint.accepts("auto"):
            return "auto"
        try:
            number = float(text)
        except ValueError:
            if info.constraint.accepts(text):
                return text
            raise argparse.ArgumentTypeError(
                f"{info.flat} must be {info.constraint.describe()}, got {text!r}"
            ) from None
        return int(number) if number.is_integer() and info.constraint.accepts(int(number)) else number

    return parse


def add_setting_flags(parser: argparse.ArgumentParser, groups: tuple[str, ...] | None = None,
                      leave_out: tuple[str, ...] = ()) -> None:
    """One flag per setting of :class:`jaxskel.FitOptions` (of ``groups`` only, when given;
    none for the flat names in ``leave_out``), with its default and doc."""
    from .pipeline._options import Choice, FitOptions

    main = parser.add_argument_group("fit settings")
    advanced = parser.add_argument_group("advanced fit settings (jaxskel.FitOptions)")
    for group, _field, info, default in FitOptions.settings():
        if (groups is not None and group not in groups) or info.flat in leave_out:
            continue
        where = advanced if info.advanced else main
        flag = _flag(info, default)
        if isinstance(default, bool) and info.cli_values is None:
            where.add_argument(flag, dest=info.flat, action="store_false" if default else "store_true",
                               default=default, help=f"turn off: {info.doc}" if default else info.doc)
            continue
        if info.cli_values:  # spelled as words on the command line, mapped by options_from_args
            shown = {v: k for k, v in info.cli_values.items()}[default]
            where.add_argument(flag, dest=info.flat, choices=list(info.cli_values), default=shown,
                               help=f"{info.doc} (default: {shown})")
            continue
        choices = None
        if isinstance(info.constraint, Choice):
            choices = [v for v in info.constraint.values if isinstance(v, str)]
        where.add_argument(flag, dest=info.flat, type=_value_type(info), default=default, choices=choices,
                           metavar=None if choices else info.flat.upper(),
                           help=f"{info.doc} (default: {'none' if default is None else default})")


def options_from_args(args: argparse.Namespace) -> FitOptions:
    """The :class:`jaxskel.FitOptions` the flags give (defaults where a namespace lacks one)."""
    from .pipeline._options import FitOptions

    given = {}
    for _, _, info, _ in FitOptions.settings():
        if hasattr(args, info.flat):
            value = getattr(args, info.flat)
            given[info.flat] = info.cli_values[value] if info.cli_values and isinstance(value, str) else value
    return FitOptions.from_settings(**given)


def _parser() -> argparse.ArgumentParser:
    from .pipeline._track import TRACK_GROUPS
    from .sd06 import AXIS_COUNTS

    p = argparse.ArgumentParser(
        prog="jaxskel",
        description="Automatic articulated skeletons from optical motion-capture markers (JAX).",
    )
    p.add_argument("--version", action="store_true", help="print the version and exit")
    sub = p.add_subparsers(dest="command")

    def output_options(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--plot", type=Path, default=None, help="write a summary figure (PNG/PDF)")
        sp.add_argument("--bvh", type=Path, default=None,
                        help="export the skeleton and motion as BVH: Y up; a human body faces +Z in a T-pose rest")
        sp.add_argument("--bvh-units", choices=("cm", "m"), default="cm", help="BVH lengths (default cm)")
        sp.add_argument("--bvh-names", choices=("mixamo", "jaxskel", "opensim", "labels"), default=None,
                        help="BVH joint names: Mixamo's (the default for a human body), the body parts', OpenSim's, "
                        "or the segment names (the default otherwise)")
        sp.add_argument("--trc-joint-centres", action="store_true",
                        help="with --trc, add the joint centres as virtual markers (RHJC, LKJC, ...)")
        sp.add_argument("--trc", type=Path, default=None,
                        help="export the fitted (gap-filled) markers as TRC (with --osim: in the model's frame, Y up, "
                        "and names, ready for OpenSim's inverse kinematics)")
        sp.add_argument("--angles", type=Path, default=None, metavar="FILE.sto",
                        help="write the anatomical joint angles of a human body as an OpenSim storage file (degrees; "
                        "Grood-Suntay axes, ISB signs: knee_l_flexion, hip_r_adduction, ...)")
        sp.add_argument("--osim", type=Path, default=None,
                        help="export the skeleton as an OpenSim 4 model (.osim): a body per segment, ball joints "
                        "(pin joints at hinges), the markers; Y up; mass and inertia are placeholders")
        sp.add_argument("--parameterize", action="store_true",
                        help="normalise the skeleton and extract joint axes/angles (Sar Dessai et al. 2006)")
        sd06 = sp.add_argument_group("--parameterize: the calibration (without one, each joint's axes come from its "
                                     "main movements, found automatically, and the default pose from every frame)")
        sd06.add_argument("--calibration", type=_calibration_window, default=None, metavar="START:END",
                          help="the frames the axes and the default pose come from: frames (0:420) or seconds, "
                          "written with a decimal point (0.0:14.0), or 'all' (every frame) or 'auto' (the default: "
                          "each joint's main movements); angles are given for every frame")
        sd06.add_argument("--calibration-trial", type=Path, default=None, metavar="FILE",
                          help="a separate calibration recording of the subject (default pose, then each joint's "
                          "movements), posed on the fitted skeleton: axes and default pose come from it")
        sd06.add_argument("--plot-angles", type=Path, default=None, metavar="FILE",
                          help="write the joint angles (PNG/PDF): a panel per joint, each axis's angle and the twist "
                          "in degrees against time, the calibration frames shaded")
        sd06.add_argument("--facing", choices=UP_AXES_CHOICES, default=None, metavar="AXIS",
                          help="the lab axis the subject faces in the default pose (x, y, z, -x, ...; write "
                          "--facing=-x), where the body itself (feet, knees, walking) does not tell front from back")
        sd06.add_argument("--axis-count", choices=AXIS_COUNTS, default=None,
                          help="where a joint's axis count comes from: 'anatomy' (the default: knees and elbows, "
                          "found from the skeleton's shape, one axis; the others from the data) or 'data' (every "
                          "joint from the data)")
        sp.add_argument("--overwrite", action="store_true", help="replace existing output files")
        sp.add_argument("--quiet", action="store_true", help="no progress bar or summary")

    fit = sub.add_parser("fit", help="fit a skeleton to one or more recordings of one subject")
    fit.add_argument("inputs", nargs="+", type=Path, help=".c3d, .trc, .csv or .h5 recordings")
    fit.add_argument("-o", "--output", type=Path, required=True, help="result file (.h5)")
    output_options(fit)
    load_options(fit)
    add_setting_flags(fit)

    demo = sub.add_parser("demo", help="fit the bundled real recording and write results")
    demo.add_argument("-o", "--outdir", type=Path, default=Path("jaxskel-demo"), help="output folder")
    demo.add_argument("--overwrite", action="store_true", default=True, help=argparse.SUPPRESS)
    demo.add_argument("--quiet", action="store_true")

    batch = sub.add_parser(
        "fit-batch", help="fit every recording in a folder (batched, resumable; optional Dask cluster)",
        description="Fit a skeleton to every recording under DIR: one result file per recording in OUTDIR "
        "(sub-folders kept), a summary table OUTDIR/summary.csv, finished recordings skipped on a rerun.",
    )
    batch.add_argument("directory", type=Path, help="folder of .c3d/.trc/.csv/.h5 recordings (searched recursively)")
    batch.add_argument("-o", "--outdir", type=Path, required=True, help="output folder")
    batch.add_argument("--scheduler", default=None,
                       help="Dask scheduler address (tcp://host:8786): fit on the cluster's workers")
    batch.add_argument("--workers", type=int, default=None,
                       help="start a local Dask cluster with this many worker processes (one per core)")
    batch.add_argument("--batch-size", type=int, default=8, help="most trials solved together (default 8)")
    batch.add_argument("--memory", default="auto", metavar="SIZE",
                       help="most memory the trials solved together may take, by their estimated peak, e.g. 6GB; "
                       "a longer trial is solved alone ('auto', default: half the memory available; 'none': "
                       "--batch-size alone)")
    batch.add_argument("--jobs", type=int, default=2, help="threads for reading/cleaning/writing (default 2)")
    batch.add_argument("--bone", action="append", default=[], metavar="NAME=A,S,B[;A,S,B]",
                       help="tabulate a bone by marker labels: on the segment of S, between its joints with the "
                       "segments of A and B; ';' averages several (repeatable)")
    batch.add_argument("--plot-bones", type=Path, default=None,
                       help="plot the first two --bone lengths per subject (Kirk et al. 2005, Fig. 5)")
    batch.add_argument("--overwrite", action="store_true", help="fit again even where a complete result exists")
    batch.add_argument("--quiet", action="store_true", help="no progress bar")
    load_options(batch)
    add_setting_flags(batch)

    track = sub.add_parser(
        "track", help="pose new trials on a saved skeleton (calibrate once, track many)",
        description="Inverse kinematics of each TRIAL on the skeleton of a result file (jaxskel fit CAL -o "
        "SKELETON.h5), the trials posed together in batched solves: OUTDIR/<trial>.h5 per trial, with the "
        "calibration's skeleton unchanged, its motion, joint positions, fitted and gap-filled markers and a "
        "per-frame residual. Markers are matched by label; missing ones are reported, extra ones ignored.",
    )
    track.add_argument("skeleton", type=Path, help="result file holding the calibrated skeleton (.h5)")
    track.add_argument("trials", nargs="+", type=Path, help=".c3d, .trc, .csv or .h5 recordings of the subject")
    track.add_argument("-o", "--outdir", type=Path, required=True, help="output folder")
    track.add_argument("--bvh", action="store_true", help="also write OUTDIR/<trial>.bvh, on the calibration's rig")
    track.add_argument("--trc", action="store_true", help="also write OUTDIR/<trial>.trc, the fitted markers")
    track.add_argument("--angles", action="store_true",
                       help="also write OUTDIR/<trial>.sto, the joint angles (the calibration must name a human body)")
    track.add_argument("--overwrite", action="store_true", help="replace existing output files")
    track.add_argument("--batch-size", type=int, default=16, help="most trials posed by one solve (default 16)")
    track.add_argument("--scheduler", default=None, help="Dask scheduler address: track on the cluster's workers")
    track.add_argument("--workers", type=int, default=None,
                       help="start a local Dask cluster with this many worker processes")
    track.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    load_options(track)
    add_setting_flags(track, groups=TRACK_GROUPS, leave_out=("ik",))

    info = sub.add_parser("info", help="describe a recording or a result file")
    info.add_argument("file", type=Path)
    load_options(info)
    return p


#: the axes ``--facing`` takes
UP_AXES_CHOICES = ("x", "y", "z", "-x", "-y", "-z")


def _calibration_window(text: str) -> tuple[int, int] | tuple[float, float] | str:
    """``--calibration START:END``: frames (whole numbers) or seconds (with a decimal point); or "all" / "auto"."""
    if text.strip().lower() in ("all", "auto"):
        return text.strip().lower()
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        if "." in text:
            start, stop = float(parts[0]), float(parts[1])
        else:
            start, stop = int(parts[0]), int(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--calibration takes START:END, frames (0:420) or seconds with a decimal point (0.0:14.0), or 'all' or "
            f"'auto'; got {text!r}"
        ) from None
    if not 0 <= start < stop:
        raise argparse.ArgumentTypeError(f"--calibration {text}: START must be >= 0 and below END")
    return start, stop


#: the file kind (jaxskel.io._output_check.OUTPUT_KINDS) each output flag of ``jaxskel fit`` writes
FIT_OUTPUTS = {"-o": "result", "--plot": "image", "--plot-angles": "image", "--bvh": "bvh", "--trc": "trc",
               "--osim": "osim", "--angles": "sto"}


def load_options(parser: argparse.ArgumentParser) -> None:
    """``--units`` and ``--up-axis``: how the recordings are read (:func:`jaxskel.load`'s ``units=``, ``up_axis=``)."""
    from ._errors import InputError
    from .io import UP_AXES, check_load_arguments

    def unit(text: str) -> str:
        try:
            check_load_arguments(text, None)
        except InputError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text

    group = parser.add_argument_group("reading the recordings")
    group.add_argument("--units", type=unit, default=None, metavar="UNIT",
                       help="length unit of the .c3d/.trc/.csv values (mm, cm, m, in, ...), overriding what the "
                       "files state or the guess where they state none; HDF5 trials are always metres")
    group.add_argument("--up-axis", dest="up_axis", choices=UP_AXES, default=None, metavar="AXIS",
                       help=f"the vertical axis ({', '.join(UP_AXES)}; write --up-axis=-z for a negative one), "
                       "overriding the files and the inference from the data")


def _load_kwargs(path: Path, args: argparse.Namespace) -> dict[str, Any]:
    """:func:`jaxskel.load`'s ``units=`` and ``up_axis=`` from the flags (no unit for HDF5 trials: always metres)."""
    units = getattr(args, "units", None)
    if path.suffix.lower() in (".h5", ".hdf5"):
        units = None
    return {"units": units, "up_axis": getattr(args, "up_axis", None)}


def _print_load_report(path: Path, trial: Any) -> None:
    """What loading dropped, renamed or found empty (:func:`jaxskel.io.load_report`), a line each."""
    from .io import load_report

    for line in load_report(trial.metadata):
        print(f"{path}: {line}")


def _check_outputs(inputs: list[Path], outputs: dict[str, Path | None], overwrite: bool) -> None:
    """Before any work, for each output flag of :data:`FIT_OUTPUTS` given: it names no input
    (even with ``--overwrite``) and no other output, it is a file name (not a folder) of a
    type its writer knows, an existing file is replaced only with ``--overwrite``, and the
    folder it goes into (or the nearest existing one above) is writable."""
    import jaxskel

    from .io import check_output, refuse_input

    named: dict[str, str] = {}
    for flag, path in outputs.items():
        if path is None:
            continue
        refuse_input(path, inputs, flag)
        key = os.path.abspath(path)
        if key in named:
            raise jaxskel.InputError(f"{named[key]} and {flag} both name {path}; give each output its own file")
        named[key] = flag
        check_output(path, FIT_OUTPUTS[flag], flag)
        if path.exists() and not overwrite:
            raise jaxskel.InputError(f"{path} exists; pass --overwrite to replace it")


def _check_batch_outputs(args: argparse.Namespace, summary: str = "summary.csv") -> None:
    """Before any work, the outputs of ``jaxskel fit-batch``: ``-o`` is (or will be) a folder
    that does not hold the input folder and can be written; no result file, nor the summary
    table, nor ``--plot-bones`` names an input recording, a folder or another output; and
    the plot has an image type matplotlib writes."""
    import jaxskel

    from .io import check_output, check_writable
    from .pipeline._batch import _resolve_items

    outdir, directory = args.outdir, args.directory
    hint = outdir.with_suffix("") if outdir.suffix else outdir.parent / f"{outdir.name}-results"
    folder_text = "fit-batch writes a folder (one result file per recording, and summary.csv)"
    if outdir.exists() and not outdir.is_dir():
        raise jaxskel.InputError(f"-o {outdir} is a file, but {folder_text}: give a folder name, e.g. -o {hint}")
    if not outdir.exists() and outdir.suffix.lower() in (".h5", ".hdf5", ".csv"):
        raise jaxskel.InputError(
            f"-o {outdir} is a file name, but {folder_text}: give a folder name, e.g. -o {hint}"
        )
    if outdir.resolve() == directory.resolve() or outdir.resolve() in directory.resolve().parents:
        same = "is" if outdir.resolve() == directory.resolve() else "holds"
        raise jaxskel.InputError(
            f"-o {outdir} {same} the input folder {directory}, and fit-batch leaves out every file under its "
            f"output folder when it looks for recordings: give another output folder, e.g. -o {directory / 'results'}"
        )
    check_writable(outdir, "-o", folder=True)
    items = _resolve_items(directory, outdir, None, None)
    inputs = {Path(v).resolve(): Path(v) for it in items for v in it.inputs}
    inodes = {(st.st_dev, st.st_ino): p for p, st in ((p, p.stat()) for p in inputs.values())}

    def input_named(path: Path) -> Path | None:
        if path.resolve() in inputs:
            return inputs[path.resolve()]
        if path.exists():
            st = path.stat()
            return inodes.get((st.st_dev, st.st_ino))
        return None

    table = outdir / summary
    outputs = {table.resolve(): "the summary table"}
    for it in items:
        src = input_named(it.output)
        if src is not None:
            raise jaxskel.InputError(
                f"the result file of {it.name}, {it.output}, is the input recording {src}; jaxskel never writes "
                "over an input: give another output folder"
            )
        if it.output.is_dir():
            raise jaxskel.InputError(
                f"the result file of {it.name}, {it.output}, is a folder; move it away or give another output folder"
            )
        outputs[it.output.resolve()] = f"the result file of {it.name}"
        if it.output.parent != outdir:
            check_writable(it.output, f"the result file of {it.name},")
    if table.is_dir():
        raise jaxskel.InputError(f"the summary table {table} is a folder; move it away or give another output folder")
    if args.plot_bones is not None:
        plot = args.plot_bones
        src = input_named(plot)
        if src is not None:
            raise jaxskel.InputError(
                f"--plot-bones {plot} is the input recording {src}; jaxskel never writes over an input, even "
                "with overwrite: choose another name"
            )
        if plot.resolve() in outputs:
            raise jaxskel.InputError(
                f"--plot-bones {plot} is {outputs[plot.resolve()]}; give the plot its own file"
            )
        check_output(plot, "image", "--plot-bones")
        if plot.exists() and not args.overwrite:
            raise jaxskel.InputError(f"{plot} exists; pass --overwrite to replace it")


def _write_angles(result: Any, path: Path | None, overwrite: bool, written: list[Path]) -> Exception | None:
    """Write ``--angles`` (the joint angles as ``.sto``) where given and the body is human;
    returns why not (the fit's other outputs stand), else None."""
    import jaxskel
    from .result import write_angles_sto

    if path is None:
        return None
    try:
        angles = result.joint_angles()
    except jaxskel.InputError as error:
        return error
    write_angles_sto(angles, path, overwrite=overwrite)
    written.append(path)
    return None


def _fit(inputs: list[Path], output: Path, args: argparse.Namespace) -> int:
    import jaxskel

    quiet = getattr(args, "quiet", False)
    options = options_from_args(args)
    osim, angles = getattr(args, "osim", None), getattr(args, "angles", None)
    window, calibration_trial = getattr(args, "calibration", None), getattr(args, "calibration_trial", None)
    plot_angles = getattr(args, "plot_angles", None)
    given = [flag for flag, value in (("--calibration", window), ("--calibration-trial", calibration_trial),
                                      ("--facing", getattr(args, "facing", None)), ("--plot-angles", plot_angles),
                                      ("--axis-count", getattr(args, "axis_count", None)))
             if value is not None]
    if given and not args.parameterize:
        raise jaxskel.InputError(f"{', '.join(given)} set(s) up --parameterize; add --parameterize")
    if window is not None and calibration_trial is not None:
        raise jaxskel.InputError("give --calibration or --calibration-trial, not both")
    if calibration_trial is not None and not calibration_trial.is_file():
        raise jaxskel.InputError(f"--calibration-trial {calibration_trial}: no such recording")
    _check_outputs(inputs, {"-o": output, "--plot": args.plot, "--plot-angles": plot_angles, "--bvh": args.bvh,
                            "--trc": args.trc, "--osim": osim, "--angles": angles}, args.overwrite)
    needs_motion = [flag for flag, on in (("--parameterize", args.parameterize), ("--plot-angles", plot_angles),
                                          ("--bvh", args.bvh), ("--trc", args.trc), ("--osim", osim),
                                          ("--angles", angles)) if on]
    if needs_motion and not (options.skeleton.enabled and options.motion.enabled):  # before any work
        raise jaxskel.InputError(
            f"{', '.join(needs_motion)} need(s) the rigid skeleton and IK; drop --no-rigid / --no-ik"
        )
    if angles is not None and not options.body.enabled:
        raise jaxskel.InputError("--angles needs the named body; drop --no-anatomy")
    if output.parent and not output.parent.exists():
        output.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    trials = [jaxskel.load(p, **_load_kwargs(p, args)) for p in inputs]
    if not quiet:
        for path, trial in zip(inputs, trials):
            _print_load_report(path, trial)
    if osim is not None and any(t.up_axis == "unknown" for t in trials):
        raise jaxskel.InputError(
            "--osim turns the recording's up axis to OpenSim's Y, but it is unknown here: give it with --up-axis"
        )
    result = jaxskel.fit_skeleton(trials, options=options, progress=not quiet)
    if result.motion is None and needs_motion:
        # the fit could not build the rigid skeleton (its warning says why): keep what it found, then say so
        result.save(output, overwrite=args.overwrite)
        if args.plot is not None:
            from .plots import plot_summary

            plot_summary(result, args.plot, overwrite=args.overwrite)
        kept = ", ".join(str(w) for w in (output, args.plot) if w is not None)
        raise jaxskel.InputError(
            f"this fit has no rigid skeleton and motion (the warning above says why), so {', '.join(needs_motion)} "
            f"could not be written; {kept} hold(s) its segments, tree and joint centres"
        )
    extra_groups, sd06_error = {}, None
    if args.parameterize:
        from .sd06 import AXIS_COUNTS, normalize, parameterize, write_normalized, write_parameters

        up = _up(result.trial.up_axis)
        axis_count = args.axis_count or AXIS_COUNTS[0]
        try:
            if calibration_trial is not None:  # posed on the fitted skeleton, as jaxskel track poses a take
                tracked = jaxskel.track(result.skeleton,
                                        jaxskel.load(calibration_trial, **_load_kwargs(calibration_trial, args)))
                if tracked.failed:
                    raise jaxskel.InputError(f"--calibration-trial {calibration_trial}: {tracked[0].error}")
                params = parameterize(result.skeleton, result.motion, up_axis=up, calibration=tracked[0].result.motion,
                                      facing=args.facing, axis_count=axis_count)
                norm = params.normalization
            else:
                norm = normalize(result.skeleton, result.motion, up_axis=up, calibration=window, facing=args.facing)
                params = parameterize(result.skeleton, result.motion, norm, calibration=window,
                                      axis_count=axis_count)
        except (jaxskel.InputError, jaxskel.DegenerateMotionError) as error:
            # the fit stands without its parameterisation: write the rest, then say why (below)
            sd06_error = error
        else:
            extra_groups = {
                "normalized": lambda g: write_normalized(g, norm),
                "parameters": lambda g: write_parameters(g, params),
            }
    result.save(output, overwrite=args.overwrite, extra_groups=extra_groups)
    written = [output]
    if args.plot is not None:
        from .plots import plot_summary

        plot_summary(result, args.plot, overwrite=args.overwrite)
        written.append(args.plot)
    if plot_angles is not None and sd06_error is None:
        from .plots import plot_joint_angles

        segments = result.skeleton.names()
        names = [f"{segments[a]}-{segments[b]}" for a, b in params.normalization.edges]
        figure = plot_joint_angles(params, names=names, rate=result.trial.rate, path=plot_angles,
                                   overwrite=args.overwrite)
        import matplotlib.pyplot as plt

        plt.close(figure)
        written.append(plot_angles)
    if args.bvh is not None:
        result.export_bvh(args.bvh, overwrite=args.overwrite, units=args.bvh_units, names=args.bvh_names)
        written.append(args.bvh)
    if args.trc is not None:
        from .result import fitted_markers_trial

        fitted = fitted_markers_trial(result.trial, result.skeleton, result.motion,
                                      joint_centres=args.trc_joint_centres, anatomy=result.anatomy)
        if osim is not None:  # the model's frame and names: the TRC OpenSim's IK reads with the model
            from .result import opensim_names, to_opensim_frame

            fitted = fitted.replace(positions=to_opensim_frame(fitted.positions, fitted.up_axis),
                                    labels=opensim_names(fitted.labels), up_axis="y")
        jaxskel.save_trial(fitted, args.trc, overwrite=args.overwrite)
        written.append(args.trc)
    if osim is not None:
        result.export_osim(osim, overwrite=args.overwrite)
        written.append(osim)
    angles_error = _write_angles(result, angles, args.overwrite, written)
    if not quiet:
        print(result.summary())
        print(f"wrote {', '.join(str(w) for w in written)} in {time.perf_counter() - t0:.1f} s")
    if angles_error is not None:
        raise jaxskel.InputError(f"--angles {angles} was not written: {angles_error}; written: "
                                 f"{', '.join(str(w) for w in written)}")
    if sd06_error is not None:
        skipped = f" and {plot_angles} was not written" if plot_angles is not None else ""
        raise type(sd06_error)(
            f"--parameterize failed: {sd06_error}. So {output} holds the fit without its parameterisation{skipped}; "
            f"written: {', '.join(str(w) for w in written)}"
        )
    return 0


def _fit_batch(args: argparse.Namespace) -> int:
    import jaxskel

    from .pipeline import parse_bone_spec, parse_memory

    memory = parse_memory(args.memory)
    if not args.directory.is_dir():
        raise jaxskel.InputError(f"{args.directory}: not a directory; fit-batch takes a folder of recordings")
    bones = dict(parse_bone_spec(text) for text in args.bone)
    if args.plot_bones is not None and len(bones) < 2:
        raise jaxskel.InputError("--plot-bones needs two --bone NAME=A,S,B options (x and y)")
    _check_batch_outputs(args)
    with _dask_cluster(args) as scheduler:
        batch = jaxskel.fit_batch(
            args.directory, args.outdir, options=options_from_args(args), bones=bones, batch_size=args.batch_size,
            memory=memory, jobs=args.jobs, scheduler=scheduler, overwrite=args.overwrite, progress=not args.quiet,
            units=args.units, up_axis=args.up_axis,
        )
    if args.plot_bones is not None:
        x, y = list(bones)[:2]
        jaxskel.pipeline.plot_bone_lengths(batch, x, y, path=args.plot_bones, overwrite=args.overwrite)
    counts = batch.counts()
    if not args.quiet:
        print(f"{len(batch)} trials: {counts.get('ok', 0)} fitted, {counts.get('skipped', 0)} already done, "
              f"{counts.get('failed', 0)} failed in {batch.seconds:.1f} s; summary: {batch.summary}")
    for o in batch.failed:
        print(f"jaxskel: {o.name}: {o.error}", file=sys.stderr)
    return 1 if batch.failed else 0


def _track(args: argparse.Namespace) -> int:
    import jaxskel

    if args.batch_size < 1:
        raise jaxskel.InputError(f"--batch-size must be at least 1, got {args.batch_size}")
    from .pipeline._track import track_settings

    settings = track_settings(options_from_args(args))
    with _dask_cluster(args) as scheduler:
        batch = jaxskel.track(
            args.skeleton, list(args.trials), args.outdir, bvh=args.bvh, trc=args.trc, angles=args.angles,
            overwrite=args.overwrite, batch_size=args.batch_size, scheduler=scheduler, progress=not args.quiet, units=args.units,
            up_axis=args.up_axis, **settings,
        )
    if not args.quiet:
        for o in batch:
            if o.result is not None:
                print(o.result.summary())
        counts = batch.counts()
        print(f"{len(batch)} trials: {counts.get('ok', 0)} tracked, {counts.get('failed', 0)} failed in "
              f"{batch.seconds:.1f} s; results in {args.outdir}")
    for o in batch.failed:
        print(f"jaxskel: {o.name}: {o.error}", file=sys.stderr)
    return 1 if batch.failed else 0


@contextlib.contextmanager
def _dask_cluster(args: argparse.Namespace) -> Iterator[Any]:
    """The Dask scheduler ``--scheduler`` names, or a local cluster of ``--workers`` processes
    (closed on exit), or None."""
    import jaxskel

    if args.scheduler and args.workers:
        raise jaxskel.InputError("give --scheduler or --workers, not both")
    if args.workers is not None and args.workers < 1:
        raise jaxskel.InputError(f"--workers must be at least 1, got {args.workers}")
    if not args.workers:
        yield args.scheduler
        return
    try:
        from distributed import LocalCluster
    except ImportError:
        raise jaxskel.InputError('--workers needs Dask: pip install "jaxskel[distributed]"') from None
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def _up(axis: str) -> str:
    return "z" if axis == "unknown" else axis


def _demo(args: argparse.Namespace) -> int:
    from .io import sample_path

    outdir = args.outdir
    outdir.mkdir(parents=True, exist_ok=True)
    ns = argparse.Namespace(
        plot=outdir / "summary.png", bvh=outdir / "skeleton.bvh", trc=outdir / "fitted_markers.trc",
        angles=outdir / "joint_angles.sto", bvh_units="cm", bvh_names=None, trc_joint_centres=False,
        parameterize=False, overwrite=True, quiet=args.quiet,
    )  # and every setting at its default (options_from_args)
    if not args.quiet:
        print(f"fitting the bundled sample {sample_path().name} (see jaxskel/data/ATTRIBUTION.md)")
    return _fit([sample_path()], outdir / "result.h5", ns)


def _info(path: Path, args: argparse.Namespace) -> int:
    import jaxskel

    if path.suffix.lower() in (".h5", ".hdf5"):
        import h5py

        try:
            with h5py.File(path, "r") as f:
                is_result = "schema_version" in f.attrs
        except OSError as exc:
            raise jaxskel.InputError(f"{path}: cannot read as HDF5 ({exc})") from None
        if is_result:
            r = jaxskel.load_result(path)
            print(f"result file {path} (schema {r.attrs['schema_version']}, jaxskel {r.attrs['jaxskel_version']})")
            print(f"  source: {r.attrs['source']}  rate: {r.attrs['rate']} Hz")
            if r.attrs.get("kind") == "tracked":
                print(f"  tracked on the skeleton of {r.attrs.get('calibration') or 'a skeleton given in memory'}")
            root = int(r.topology.root)
            print(f"  {len(r.markers.labels)} input markers, {len(r.segments.names)} segments, "
                  f"{len(r.topology.edges)} joints, root {r.segments.names[root]} (segment {root})")
            print(f"  segments: {', '.join(r.segments.names)}")
            if "anatomy" in r:
                parts = [str(p) for p in r.anatomy.segment_part]
                print(f"  body: {'human' if r.anatomy.attrs['humanoid'] else 'not human'}, "
                      f"{sum(map(bool, parts))} of {len(parts)} segments named")
            print(f"  groups: {', '.join(r.keys())}")
            return 0
    trial = jaxskel.load(path, **_load_kwargs(path, args))
    print(trial)
    _print_load_report(path, trial)
    print(f"  labels: {', '.join(trial.labels)}")
    present = trial.mask.mean(axis=0)
    gappy = [lab for lab, p in zip(trial.labels, present) if p < 1]
    print(f"  {len(gappy)} markers with gaps; metadata: {dict(trial.metadata)}")
    return 0


#: The subcommands that fit (and so read their solver programs ahead).
_FITTING = ("fit", "demo", "fit-batch", "track")


def main(argv: list[str] | None = None) -> int:
    own_process()  # the command's process is jaxskel's own: single-threaded Eigen, before JAX starts
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((word for word in argv if not word.startswith("-")), None)
    if command is not None and not {"-h", "--help"} & set(argv):
        # before the stages' modules import: a fitting command reads its compiled programs meanwhile
        enable_compile_cache(read_ahead=command in _FITTING)
    args = _parser().parse_args(argv)
    if args.version:
        from ._version import __version__

        print(f"jaxskel {__version__}")
        return 0
    if args.command is None:
        _parser().print_help()
        return 1
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning
        return _run(args)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
    """Warnings as a command line tool says them: one labelled message on a line of its own,
    no source line; a trial's warning of ``fit-batch`` names the trial
    (``jaxskel: warning (Category) [trial]: message``, :mod:`jaxskel.pipeline._trial_warnings`)."""
    trial = getattr(message, "trial", None)
    head = f"jaxskel: warning ({category.__name__})" + (f" [{trial}]" if trial is not None else "")
    text = getattr(message, "text", message) if trial is not None else message
    _say(f"{head}: {text}", sys.stderr if file is None else file)


def _say(text: str, stream: Any) -> None:
    """Write ``text`` as lines of their own while a progress bar may be drawn on ``stream``.

    A tqdm bar leaves the cursor at the end of its line; a message written there would
    continue the bar's line. Active bars are cleared first and drawn again below the
    message (tqdm's external write mode); where the stream is not a terminal (a log
    file, a pipe), clearing only writes a carriage return, so the message also starts
    with a newline.
    """
    tqdm = sys.modules.get("tqdm")  # a bar exists only where tqdm was imported
    bars = [] if tqdm is None else [b for b in list(getattr(tqdm.tqdm, "_instances", ())) if not b.disable]
    if not bars:
        print(text, file=stream)
        return
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):
        tty = False
    with tqdm.tqdm.external_write_mode(file=stream):
        stream.write(("" if tty else "\n") + text + "\n")
        stream.flush()


def _run(args: argparse.Namespace) -> int:
    from ._errors import JaxskelError

    try:
        if args.command == "fit":
            return _fit(args.inputs, args.output, args)
        if args.command == "demo":
            return _demo(args)
        if args.command == "info":
            return _info(args.file, args)
        if args.command == "fit-batch":
            return _fit_batch(args)
        if args.command == "track":
            return _track(args)
    except JaxskelError as exc:
        print(f"jaxskel: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxskel: interrupted; no partial output was left behind", file=sys.stderr)
        return 130
    except OSError as exc:  # the system refused a write the preflight allowed (disk full, permissions changed)
        print(f"jaxskel: error: {exc}; no partial output was left behind", file=sys.stderr)
        return 1
    return 1


def run() -> NoReturn:
    """The ``jaxskel`` command: :func:`main`, then exit without tearing the interpreter down.

    Python's own exit frees every module, and with them JAX's compiled programs one
    mapping at a time: 0.5-0.8 s at the end of a fit that only returns memory the
    operating system takes back at once. Everything an exit must do still happens: the
    ``atexit`` handlers run (logging's flush, temporary folders, jaxskel's read-ahead
    thread) and the output streams are flushed; then the process ends with
    :func:`os._exit`. Where a thread that is not a daemon still runs (a library's pool
    left open), or an exception escapes :func:`main` (a bug), the process takes Python's
    usual way out, which shuts such threads down in its own order.
    """
    code = main()
    here = threading.current_thread()
    if any(t is not here and not t.daemon and t.is_alive() for t in threading.enumerate()):
        sys.exit(code)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing left to say
            pass
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
