"""Settings of :func:`jaxskel.anatomy.identify`."""

from __future__ import annotations

import dataclasses
import math

from .._errors import InputError

__all__ = ["AnatomyOptions"]


@dataclasses.dataclass(frozen=True)
class AnatomyOptions:
    """How :func:`jaxskel.anatomy.identify` decides (every length in metres).

    Attributes
    ----------
    limb_match
        Largest relative difference between the spans (the two longest consecutive
        bones: thigh + shank, upper arm + forearm) of two limbs taken as a mirror pair.
        The two sides of a body agree to a few per cent, a fit to ~15 %; a leg and an arm
        differ by a third.
    min_side_evidence
        Smallest side evidence (in [0, 1]: how consistently, over the frames, the
        limbs' hinges and feet say which of two limbs is the left one) to name sides;
        below it the limbs are left ``""`` rather than risk a swap. A pair of limbs
        without that much evidence is not taken as a human pair either.
    min_leg_span
        A lone pair of limbs (no second pair to compare with) at least this long
        (thigh + shank of an adult: 0.75-0.9 m; upper arm + forearm: 0.5-0.6 m) is a
        pair of legs, a shorter one a pair of arms.
    clavicle_ratio
        A segment proximal to the upper arm whose length is at most this fraction of
        the upper arm's is a clavicle.
    axis_snap_deg
        With ``up_axis="auto"``, the measured up direction is replaced by the nearest
        signed lab axis when it lies within this angle of it (degrees, 0 never).
    twig_markers, twig_ratio
        A leaf segment with at most ``twig_markers`` markers is a *twig* (a marker over a
        joint or a landmark, split off its segment; not a chain of its own) when it hangs
        from a segment with two other neighbours, or when its joint lies within
        ``twig_ratio`` of its host's extent from another joint of the host. A twig on a
        joint takes the part proximal of that joint, another twig its host's. A toe
        segment starts at the far end of its foot (about 0.7 of the foot's extent from
        the ankle), an ankle marker split off a foot at 0.2-0.35.
    max_frames
        At most this many frames of the motion, spread evenly, are used.
    """

    limb_match: float = 0.2
    min_side_evidence: float = 0.5
    min_leg_span: float = 0.68
    clavicle_ratio: float = 0.6
    axis_snap_deg: float = 30.0
    twig_markers: int = 1
    twig_ratio: float = 0.4
    max_frames: int = 2000

    def __post_init__(self) -> None:
        def number(name: str, lo: float, hi: float) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                raise InputError(f"AnatomyOptions.{name} must be a number in [{lo}, {hi}]; got {v!r}")

        number("limb_match", 0.0, 1.0)
        number("min_side_evidence", 0.0, 1.0)
        number("min_leg_span", 0.0, 10.0)
        number("clavicle_ratio", 0.0, 1.0)
        number("axis_snap_deg", 0.0, 90.0)
        number("twig_ratio", 0.0, 1.0)
        if isinstance(self.twig_markers, bool) or not isinstance(self.twig_markers, int) or self.twig_markers < 0:
            raise InputError(f"AnatomyOptions.twig_markers must be a non-negative integer; got {self.twig_markers!r}")
        if isinstance(self.max_frames, bool) or not isinstance(self.max_frames, int) or self.max_frames < 1:
            raise InputError(f"AnatomyOptions.max_frames must be a positive integer; got {self.max_frames!r}")
