"""`FitOptions`: every setting of a fit, once, with its default, its bounds and its doc.

One frozen, validated object, grouped by stage (as jaxls groups its solver settings)::

    FitOptions(
        clean=CleanOptions(...),        # jaxskel.clean.clean
        labels=LabelOptions(...),       # jaxskel.relabel.merge_labels / confirm_merges
        segment=SegmentOptions(...),    # jaxskel.segment.segment_markers
        joints=JointOptions(...),       # jaxskel.joints.joint_costs / fit_topology
        skeleton=SkeletonOptions(...),  # jaxskel.skeleton.fit_rigid
        motion=MotionOptions(...),      # jaxskel.skeleton.inverse_kinematics
        seed=0,
    )

Every field is declared with :func:`setting`: its default, a constraint (an interval, a
set of choices, a type), one line of documentation and its *flat name*, which is unique
across the groups. The flat names are what :func:`jaxskel.fit_skeleton` and
:func:`jaxskel.fit_batch` take as keyword overrides (``fit_skeleton(trial, sigma=0.006)``)
and what the command line's flags are made of (``--sigma``; a switch that defaults to on
becomes ``--no-...``): the three entry points cannot disagree on a setting, its default or
its bounds. Validation runs once, on construction (as scikit-learn's
``_parameter_constraints``); a bad value raises :class:`jaxskel.InputError` naming the
setting, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import math
from collections.abc import Iterator, Mapping
from typing import Any

from .._errors import InputError

__all__ = [
    "CleanOptions", "FitOptions", "JointOptions", "LabelOptions", "MotionOptions", "SegmentOptions",
    "SettingInfo", "SkeletonOptions", "setting",
]


# ------------------------------------------------------------------ constraints
@dataclasses.dataclass(frozen=True)
class Interval:
    """A real (or, with ``integer``, whole) number in ``[low, high]`` (open ends where asked)."""

    low: float | None = None
    high: float | None = None
    integer: bool = False
    open_low: bool = False
    open_high: bool = False

    def accepts(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if self.integer and not float(value).is_integer():
            return False
        v = float(value)
        if not math.isfinite(v):
            return False
        if self.low is not None and (v < self.low or (self.open_low and v == self.low)):
            return False
        return not (self.high is not None and (v > self.high or (self.open_high and v == self.high)))

    def describe(self) -> str:
        kind = "a whole number" if self.integer else "a number"
        lo = "" if self.low is None else f"{'>' if self.open_low else '>='} {self.low:g}"
        hi = "" if self.high is None else f"{'<' if self.open_high else '<='} {self.high:g}"
        return " ".join(p for p in (kind, lo, "and" if lo and hi else "", hi) if p)


@dataclasses.dataclass(frozen=True)
class Choice:
    """One of a fixed set of values."""

    values: tuple[Any, ...]

    def accepts(self, value: Any) -> bool:
        return any(value is v or (type(value) is type(v) and value == v) for v in self.values)

    def describe(self) -> str:
        return "one of " + ", ".join(repr(v) for v in self.values)


@dataclasses.dataclass(frozen=True)
class AnyOf:
    """Accepted by any of several constraints (``None`` accepts ``None``)."""

    options: tuple[Any, ...]
    #: how an error message names the accepted values (default: each option's own words)
    what: str | None = None

    def accepts(self, value: Any) -> bool:
        return any(value is None if c is None else c.accepts(value) for c in self.options)

    def describe(self) -> str:
        return self.what or " or ".join("None" if c is None else c.describe() for c in self.options)


@dataclasses.dataclass(frozen=True)
class IsInstance:
    """A value of the given types (bool is never taken for int)."""

    types: tuple[type, ...]
    what: str

    def accepts(self, value: Any) -> bool:
        if isinstance(value, bool) and bool not in self.types:
            return False
        return isinstance(value, self.types)

    def describe(self) -> str:
        return self.what


BOOL = IsInstance((bool,), "True or False")


@dataclasses.dataclass(frozen=True)
class SettingInfo:
    """What a setting is: its flat name, constraint, doc and command-line flag."""

    flat: str
    constraint: Any
    doc: str
    #: the command-line flag, ``None`` for ``--<flat name with dashes>`` (``--no-...`` for a
    #: switch that defaults to on); ``""`` for a setting with no flag
    flag: str | None = None
    #: how the command line spells a value (``{"yes": True}``), where it is not the value itself
    cli_values: Mapping[str, Any] | None = None
    advanced: bool = False


def setting(
    default: Any, constraint: Any, doc: str, *, flat: str, flag: str | None = None,
    cli_values: Mapping[str, Any] | None = None, advanced: bool = True,
) -> Any:
    """A field of an options group: its default and its :class:`SettingInfo`."""
    info = SettingInfo(flat=flat, constraint=constraint, doc=doc, flag=flag, cli_values=cli_values,
                       advanced=advanced)
    return dataclasses.field(default=default, metadata={"setting": info})


class _Group:
    """Validation shared by the option groups (frozen dataclasses)."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            info: SettingInfo = f.metadata["setting"]
            value = getattr(self, f.name)
            if isinstance(value, float) and value.is_integer() and isinstance(info.constraint, Interval) \
                    and info.constraint.integer:
                object.__setattr__(self, f.name, int(value))
                value = int(value)
            if not info.constraint.accepts(value):
                raise InputError(
                    f"{info.flat} must be {info.constraint.describe()}, got {value!r} ({info.doc})"
                )


_NONNEG = Interval(0.0)
_POS = Interval(0.0, open_low=True)


@dataclasses.dataclass(frozen=True)
class CleanOptions(_Group):
    """Cleaning (:func:`jaxskel.clean.clean`; Kirk et al. 2005, sec. 3)."""

    enabled: bool = setting(True, BOOL, "clean the data first (gap-edge trimming, jump rejection)",
                            flat="clean_data", flag="--no-clean", advanced=False)
    trim_s: float = setting(0.02, _NONNEG, "seconds trimmed at each gap-adjacent run end (0: none)", flat="trim_s")
    min_run_s: float = setting(0.5, _NONNEG, "markers whose longest run is shorter are dropped (seconds)",
                               flat="min_run_s")
    reject_jumps: bool = setting(True, BOOL, "reject samples that jump off their trajectory", flat="reject_jumps",
                                 flag="--no-reject-jumps")
    jump_threshold: float = setting(0.02, _NONNEG, "smallest deviation taken for a jump (metres)",
                                    flat="jump_threshold")
    jump_mad_factor: float = setting(8.0, _POS, "jump limit in robust standard deviations of a marker's deviations",
                                     flat="jump_mad_factor")
    jump_window_s: float = setting(0.1, _NONNEG, "running-median window of the jump test (seconds)",
                                   flat="jump_window_s")
    duplicate_tolerance: float = setting(0.001, _NONNEG, "two labels never further apart are one marker "
                                         "(metres; 0: no merging of duplicates)", flat="duplicate_tolerance")
    duplicate_min_s: float = setting(0.5, _NONNEG, "seconds two labels must be seen together to be duplicates",
                                     flat="duplicate_min_s")

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`jaxskel.clean.clean`."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "enabled"}


@dataclasses.dataclass(frozen=True)
class LabelOptions(_Group):
    """Merging the labels of one physical marker (:func:`jaxskel.relabel.merge_labels`)."""

    merge: bool | str = setting(
        "auto", Choice(("auto", True, False)),
        "merge relabelled passive markers: 'auto' (more labels than markers in any frame and unnamed *N "
        "trajectories), True or False", flat="merge_labels", cli_values={"auto": "auto", "yes": True, "no": False},
        advanced=False)
    confirm: bool = setting(True, BOOL, "check the merges against the fitted skeleton and refit if it corrects any",
                            flat="confirm_merges", flag="--no-confirm-merges")


@dataclasses.dataclass(frozen=True)
class SegmentOptions(_Group):
    """Grouping markers into rigid segments (:func:`jaxskel.segment.segment_markers`)."""

    n_segments: int | None = setting(None, AnyOf((None, Interval(1, integer=True))),
                                     "number of segments (None: the eigengap's, grown toward rigid groups)",
                                     flat="n_segments", flag="--segments", advanced=False)
    n_samplings: int = setting(8, Interval(1, integer=True), "jittered frame samplings clustered",
                               flat="n_samplings")
    interval_s: float = setting(0.5, _POS, "one sampled frame every this many seconds", flat="interval_s")
    jitter_s: float = setting(0.1, _NONNEG, "jitter of the sampled frames (seconds)", flat="jitter_s")
    min_samples: int = setting(40, Interval(2, integer=True), "fewest frames a sampling takes", flat="min_samples")
    min_cooccur: int = setting(5, Interval(1, integer=True), "fewest sampled frames two markers must share",
                               flat="min_cooccur")
    sigma: float | None = setting(None, AnyOf((None, _POS)), "affinity scale in metres (None: from the noise floor)",
                                  flat="sigma")
    sigma_factor: float = setting(2.0, _POS, "affinity scale in noise floors, when sigma is None",
                                  flat="sigma_factor")
    sigma_min: float = setting(0.003, _NONNEG, "smallest affinity scale (metres)", flat="sigma_min")
    max_segments: int = setting(30, Interval(1, integer=True), "most segments the automatic count considers",
                                flat="max_segments")
    rigid_ratio: float | None = setting(3.0, AnyOf((None, _POS)),
                                        "grow the automatic count until no group holds two markers further than "
                                        "this many sigma from rigid (None: the eigengap alone)", flat="rigid_ratio")
    mend: bool = setting(True, BOOL, "move plainly misgrouped markers before scoring a clustering", flat="mend",
                         flag="--no-mend")
    leave_out: bool = setting(True, BOOL, "leave out markers the motion cannot place: those seen only while the "
                              "body held still (a static trial's extra markers) and stationary objects",
                              flat="leave_out", flag="--no-leave-out")

    def kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :func:`jaxskel.segment.segment_markers` (without the count)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in ("n_segments", "leave_out")}


@dataclasses.dataclass(frozen=True)
class JointOptions(_Group):
    """Joint costs and the tree (:func:`jaxskel.joints.joint_costs`, :func:`jaxskel.joints.fit_topology`)."""

    method: str = setting("lm", Choice(("lm", "ncg")), "joint solver", flat="method", advanced=False)
    alpha: float = setting(1e-5, _NONNEG, "weight of the distance prior in the joint cost", flat="alpha")
    alpha_tree: float | str = setting(
        "auto", AnyOf((Choice(("auto",)), _NONNEG), what="'auto' or a number >= 0"),
        "distance-prior weight of the tree joints' refit: 'auto' (0 where the motion determines the joint) or a "
        "number", flat="alpha_tree", cli_values=None)
    topology_frames: int = setting(300, Interval(10, integer=True), "frames sampled for the all-pairs joint costs",
                                   flat="topology_frames")
    pose_check: bool = setting(True, BOOL, "check tree joints between well-marked segments against their poses",
                               flat="pose_check", flag="--no-pose-check", advanced=False)
    root: int | str | None = setting(None, AnyOf((None, Interval(0, integer=True), IsInstance((str,), "a label"))),
                                     "root segment index or a marker label on it (None: the tree's centre)",
                                     flat="root", advanced=False)


@dataclasses.dataclass(frozen=True)
class SkeletonOptions(_Group):
    """The rigid skeleton (:func:`jaxskel.skeleton.fit_rigid`)."""

    enabled: bool = setting(True, BOOL, "fit the rigid skeleton (False: stop after the joints)", flat="rigid",
                            flag="--no-rigid", advanced=False)
    hinge_centres: str = setting("limb_plane", Choice(("limb_plane", "prior")),
                                 "where a hinge's centre sits along its axis", flat="hinge_centres",
                                 advanced=False)
    joint_centres: str = setting("anchored", Choice(("anchored", "per_frame")),
                                 "the joint centres the rigid skeleton is pinned to", flat="joint_centres",
                                 advanced=False)


@dataclasses.dataclass(frozen=True)
class MotionOptions(_Group):
    """Inverse kinematics (:func:`jaxskel.skeleton.inverse_kinematics`)."""

    enabled: bool = setting(True, BOOL, "run inverse kinematics (which fills gaps)", flat="ik", flag="--no-ik",
                            advanced=False)
    lowpass: float | str | None = setting(
        "auto", AnyOf((None, Choice(("auto",)), _POS), what="a low-pass cutoff: 'auto', None or a frequency in Hz (> 0)"),
        "low-pass filter of the markers IK poses: 'auto' (per marker, residual analysis), a cutoff in Hz, or None",
        flat="ik_lowpass", advanced=False)


@dataclasses.dataclass(frozen=True)
class BodyOptions(_Group):
    """The named body (:func:`jaxskel.anatomy.identify`)."""

    enabled: bool = setting(True, BOOL, "name the body parts of a human skeleton (pelvis, thigh_l, ...) and "
                            "its joints (knee_l, ...)", flat="anatomy", flag="--no-anatomy", advanced=False)


_GROUPS = {"clean": CleanOptions, "labels": LabelOptions, "segment": SegmentOptions, "joints": JointOptions,
           "skeleton": SkeletonOptions, "motion": MotionOptions, "body": BodyOptions}

#: The settings a result file records (``/diagnostics`` ``settings``), by flat name.
RECORDED = ("n_segments", "root", "clean_data", "merge_labels", "alpha", "alpha_tree", "method", "topology_frames",
            "rigid", "ik", "seed", "confirm_merges", "hinge_centres", "joint_centres", "ik_lowpass", "pose_check",
            "anatomy")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Every setting of :func:`jaxskel.fit_skeleton` and :func:`jaxskel.fit_batch`, validated.

    Build it from groups (``FitOptions(segment=SegmentOptions(n_segments=15))``) or from
    flat names (``FitOptions.from_settings(n_segments=15, ik=False)``); change it with
    :meth:`replace`. ``seed`` seeds the segmentation's samplings and clustering.

    The main settings, by flat name (every setting's one-line doc is in its field; the
    command line lists them all under ``jaxskel fit --help``):

    n_segments
        Number of rigid segments, or ``None`` for an automatic count: the eigengap's,
        grown until every group is rigid, or to the most rigid count before one that
        leaves a marker alone (:func:`jaxskel.segment.segment_markers`), and grown
        again by one, with the fit rerun, while a segment holds two or more markers the
        rigid skeleton cannot hold (:mod:`jaxskel.pipeline._split_refit`; kept only if fewer
        markers are flagged). A given count is never changed.
    root
        Root segment index or a marker label on it; default the tree's centre.
    clean_data
        Run :func:`jaxskel.clean.clean` first (recommended for raw data).
    merge_labels
        Merge relabelled passive markers (:func:`jaxskel.relabel.merge_labels`): ``True``,
        ``False``, or ``"auto"``: merge when there are more labels than the most
        markers seen in any one frame *and* the recording has unnamed (``*N``)
        trajectories. A named recording with occlusions also has more labels than
        markers per frame; merging it by default would risk joining distinct
        markers, so it only gets a warning.
    alpha, alpha_tree, method, topology_frames
        Joint solve settings (see :func:`jaxskel.joints.joint_costs`, :func:`jaxskel.joints.fit_topology`).
    rigid, ik
        Also fit the rigid skeleton and run inverse kinematics.
    confirm_merges
        After merging labels, check the merges against the fitted skeleton
        (:func:`jaxskel.relabel.confirm_merges`) and, if it corrects any, segment and fit
        again from the corrected merge. Needs ``rigid`` and ``ik``.
    hinge_centres
        Where the rigid skeleton puts a joint whose centre the markers leave free along
        an axis (``topology.undetermined > 0``: knees, elbows): ``"limb_plane"`` (default)
        in the plane of its neighbouring joints (:mod:`jaxskel.skeleton._hinge_centres`), or
        ``"prior"``: where the distance prior of the joint solve left it (the paper; it
        pulls the centre out to the markers on the skin).
    joint_centres
        The joint centres the rigid skeleton is pinned to: ``"anchored"`` (default) refits
        each joint with its centre fixed in the frame of one of its segments and moves it
        along the directions that fit resolves (:mod:`jaxskel.joints._anchored_centres`; it
        corrects centres that slide along the normal of nearly coplanar markers, such as
        hips next to four waist markers), or ``"per_frame"``: the joint
        solve's free centre per frame (the paper). The refit is reported in
        ``skeleton.diagnostics["anchored"]``, and its resolutions say how well the
        recording fixes each joint and bone (:meth:`SkeletonResult.joint_resolutions`,
        :meth:`SkeletonResult.undetermined_joints`; ``"per_frame"`` has none, NaN).
    ik_lowpass
        Low-pass filter of the markers the IK poses (:func:`jaxskel.clean.lowpass_markers`;
        the skeleton is fitted to the markers as measured): ``"auto"`` (default), a
        cutoff for each marker by residual analysis against its own white noise, which
        leaves noiseless or fast markers as they are; a frequency in Hz for every
        marker; or ``None``, no filter. The cutoffs are in ``motion.lowpass_hz``.
    pose_check
        Check the tree's joints between segments of three or more markers as points
        fixed in both segments' poses, and exchange the ones the poses reject
        (:mod:`jaxskel.joints._pose_check`, ``topology.pose_exchanges``, ``pose check:`` in the
        summary). ``False``: the minimum
        spanning tree of the joint costs as the paper has it.
    """

    clean: CleanOptions = dataclasses.field(default_factory=CleanOptions)
    labels: LabelOptions = dataclasses.field(default_factory=LabelOptions)
    segment: SegmentOptions = dataclasses.field(default_factory=SegmentOptions)
    joints: JointOptions = dataclasses.field(default_factory=JointOptions)
    skeleton: SkeletonOptions = dataclasses.field(default_factory=SkeletonOptions)
    motion: MotionOptions = dataclasses.field(default_factory=MotionOptions)
    body: BodyOptions = dataclasses.field(default_factory=BodyOptions)
    seed: int = 0

    def __post_init__(self) -> None:
        for name, cls in _GROUPS.items():
            if not isinstance(getattr(self, name), cls):
                raise InputError(f"FitOptions.{name} must be a jaxskel.pipeline.{cls.__name__}, "
                                 f"got {type(getattr(self, name)).__name__}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"seed must be a non-negative whole number, got {self.seed!r}")

    # ------------------------------------------------------------- flat names
    @staticmethod
    def settings() -> Iterator[tuple[str, str, SettingInfo, Any]]:
        """Every setting as ``(group, field, info, default)``; ``group`` is ``""`` for ``seed``."""
        for name, cls in _GROUPS.items():
            for f in dataclasses.fields(cls):
                yield name, f.name, f.metadata["setting"], f.default
        yield "", "seed", SettingInfo("seed", Interval(0, integer=True), "seeds the segmentation", advanced=False), 0

    @classmethod
    def _where(cls) -> dict[str, tuple[str, str]]:
        return _where()

    def replace(self, **settings: Any) -> FitOptions:
        """A copy with the given settings (flat names) changed, validated."""
        where = self._where()
        unknown = [k for k in settings if k not in where]
        if unknown:
            hints = []
            for k in unknown:
                close = difflib.get_close_matches(k, list(where), n=1)
                hints.append(f"{k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
            raise InputError(f"unknown setting {', '.join(hints)}; the settings are: {', '.join(sorted(where))}")
        changes: dict[str, dict[str, Any]] = {}
        top: dict[str, Any] = {}
        for k, v in settings.items():
            group, field = where[k]
            if group:
                changes.setdefault(group, {})[field] = v
            else:
                top[field] = v
        new = {g: dataclasses.replace(getattr(self, g), **c) for g, c in changes.items()}
        return dataclasses.replace(self, **new, **top)

    @classmethod
    def from_settings(cls, **settings: Any) -> FitOptions:
        """Defaults with the given settings (flat names)."""
        return cls().replace(**settings)

    def get(self, flat: str) -> Any:
        """The value of one setting by its flat name."""
        group, field = self._where()[flat]
        return getattr(getattr(self, group), field) if group else getattr(self, field)

    def as_flat(self) -> dict[str, Any]:
        """Every setting by flat name."""
        return {info.flat: self.get(info.flat) for _, _, info, _ in self.settings()}

    def record(self) -> dict[str, Any]:
        """The settings a result file records (:data:`RECORDED`)."""
        return {k: self.get(k) for k in RECORDED}


@functools.cache
def _where() -> dict[str, tuple[str, str]]:
    """Flat name -> (group, field) of every setting (fixed by the declarations: built once)."""
    return {info.flat: (group, field) for group, field, info, _ in FitOptions.settings()}
