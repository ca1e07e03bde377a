"""Virtual markers: a fit's joint centres as extra marker trajectories (for a TRC or C3D).

Joint ``j`` (``skeleton.edges[j]``, parent -> child) becomes one marker at
``motion.joint_positions[:, j]`` (metres, the recording's frame; NaN where the frame is not
posed). Its label is the lab name of the joint centre (:data:`jaxskel.anatomy.VIRTUAL_MARKER`,
Plug-in Gait style: ``RHJC`` the right hip, ``LKJC`` the left knee, ``RAJC``, ``RSJC``,
``REJC``, ``RWJC``, ...) when a humanoid :class:`jaxskel.anatomy.Anatomy` names the parts
of both its segments (:func:`jaxskel.anatomy.joint_between`: the tree's edge may run either
way), else ``<child segment>_JC`` (the segment's name as an ASCII identifier,
:func:`jaxskel.result._export_names.ascii_names`). A label the trial already has gets
``_2``, ``_3``, ... so no marker is shadowed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .._errors import InputError
from ._export_names import ascii_names

if TYPE_CHECKING:
    from ..anatomy import Anatomy
    from ..io import Trial
    from ..skeleton import Motion, Skeleton

__all__ = ["fitted_markers_trial", "joint_centre_labels", "with_joint_centres"]


def joint_centre_labels(skeleton: Skeleton, anatomy: Anatomy | None = None) -> tuple[str, ...]:
    """(J,) the virtual-marker label of every joint (module docstring), before de-duplication."""
    from ..anatomy import VIRTUAL_MARKER, joint_between

    if anatomy is not None and len(anatomy.parts) != skeleton.n_segments:
        raise InputError(f"the anatomy names {len(anatomy.parts)} segments, the skeleton has {skeleton.n_segments}")
    humanoid = anatomy is not None and anatomy.humanoid
    segment = ascii_names(skeleton.names())
    return tuple(
        (humanoid and VIRTUAL_MARKER.get(joint_between(anatomy.parts[p], anatomy.parts[c]))) or f"{segment[c]}_JC"
        for p, c in np.asarray(skeleton.edges, dtype=int).tolist()
    )


def with_joint_centres(trial: Trial, skeleton: Skeleton, motion: Motion, anatomy: Anatomy | None = None) -> Trial:
    """``trial`` with every joint centre of ``motion`` appended as a marker (module docstring).

    ``trial`` is one recording (F, M, 3) with the motion's frames; the result has
    ``M + J`` markers, the joint centres last, in joint order. Raises
    :class:`jaxskel.InputError` when the shapes disagree.
    """
    centres = np.asarray(motion.joint_positions, dtype=float)
    positions = np.asarray(trial.positions, dtype=float)
    if centres.ndim != 3 or positions.ndim != 3:
        raise InputError("with_joint_centres takes one trial; index the motion's leading trial axis first")
    if centres.shape[:2] != (positions.shape[0], skeleton.n_joints):
        raise InputError(
            f"the motion has {centres.shape[0]} frames of {centres.shape[1]} joints; the trial {positions.shape[0]} "
            f"frames and the skeleton {skeleton.n_joints} joints"
        )
    labels = ascii_names(joint_centre_labels(skeleton, anatomy), reserved=trial.labels)
    return trial.replace(positions=np.concatenate([positions, centres], axis=1),
                         labels=(*trial.labels, *labels))


def fitted_markers_trial(
    trial: Trial, skeleton: Skeleton, motion: Motion, *, joint_centres: bool = False,
    anatomy: Anatomy | None = None,
) -> Trial:
    """The fitted (gap-filled) markers ``motion.fitted_markers`` as a trial like ``trial``
    (its rate, up axis, metadata), for a TRC or C3D export; with ``joint_centres``, the
    joint centres appended as virtual markers (:func:`with_joint_centres`)."""
    fitted = trial.replace(positions=np.asarray(motion.fitted_markers, dtype=float), labels=tuple(motion.marker_labels),
                           source="jaxskel IK fit")
    return with_joint_centres(fitted, skeleton, motion, anatomy) if joint_centres else fitted
