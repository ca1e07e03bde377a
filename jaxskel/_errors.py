"""One exception family for everything jaxskel raises on purpose.

Every message says what is wrong *and* what to do about it; callers can catch
:class:`JaxskelError` to handle all of them.
"""

from __future__ import annotations

__all__ = [
    "JaxskelError",
    "InputError",
    "DegenerateMotionError",
    "SchemaError",
    "ConvergenceWarning",
    "UnitsWarning",
    "DegenerateMotionWarning",
    "TrackingWarning",
]


class JaxskelError(Exception):
    """Base class of every error jaxskel raises deliberately."""


class InputError(JaxskelError, ValueError):
    """The input (a file, an array, an argument) is malformed or unusable."""


class DegenerateMotionError(JaxskelError):
    """The motion does not contain the information a stage needs.

    Examples: a joint that is never exercised, a segment with too few markers,
    every marker lost in the same frame.
    """


class SchemaError(JaxskelError):
    """A result file was written by an incompatible jaxskel version."""


class ConvergenceWarning(UserWarning):
    """A solver stopped before meeting its tolerance; see the result's diagnostics."""


class UnitsWarning(UserWarning):
    """A file did not state its units and an assumption was made."""


class TrackingWarning(UserWarning):
    """A trial tracked on a saved skeleton lacks some of its markers, or cannot pose a
    segment in some frames (:func:`jaxskel.track`); the result says which."""


class DegenerateMotionWarning(UserWarning):
    """Part of the motion carries too little information (e.g. a joint that barely moves);
    the affected result is reported but should not be trusted."""


class AmbiguousTreeWarning(UserWarning):
    """A joint of the fitted tree costs about as much as a rival pair the tree would
    joint instead: the margin is within the sampling noise of the two costs, so the data
    do not say which is right (:func:`jaxskel.joints.near_ties`)."""


class NonRigidMarkerWarning(UserWarning):
    """The fitted rigid skeleton leaves some markers far off (residual well above the
    recording's median): soft tissue, a marker on a joint, or two segments clustered as
    one; the markers are named with a count to compare."""
