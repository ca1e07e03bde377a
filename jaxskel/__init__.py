"""jaxskel: automatic articulated skeletons from optical motion-capture markers, on JAX.

The flat public API lives here; the implementation is in small private modules
(``jaxskel.io._trial``, ``jaxskel.clean._clean``, ...). Names are imported lazily so that
``import jaxskel`` stays fast and a command-line call pays only for what it uses.

jaxskel enables JAX's 64-bit mode on import (joint fitting needs float64 accuracy;
arrays passed as float32 still compute in float32). Set ``JAXSKEL_NO_X64=1`` before
importing to leave JAX's global setting alone.

jaxskel also runs XLA's CPU backend with single-threaded Eigen
(``--xla_cpu_multi_thread_eigen=false`` in ``XLA_FLAGS``) unless ``XLA_FLAGS``
already says otherwise or ``JAXSKEL_XLA_MULTI_THREAD=1``: with the multi-threaded
Eigen pool, vmapped solves were seen to wedge for good on 2-core machines under
load (see ``jaxskel._math.linalg`` for the mechanism, and ``docs/design.md``). This only
takes effect if no JAX computation ran before ``import jaxskel``.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

from ._version import __version__  # noqa: F401  (public: jaxskel.__version__)

if not os.environ.get("JAXSKEL_XLA_MULTI_THREAD") and "xla_cpu_multi_thread_eigen" not in os.environ.get(
    "XLA_FLAGS", ""
):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()

if not os.environ.get("JAXSKEL_NO_X64"):
    import jax

    jax.config.update("jax_enable_x64", True)

# public name -> private module that defines it
_LAZY = {
    # errors
    "JaxskelError": "_errors",
    "InputError": "_errors",
    "DegenerateMotionError": "_errors",
    "SchemaError": "_errors",
    "ConvergenceWarning": "_errors",
    "UnitsWarning": "_errors",
    "DegenerateMotionWarning": "_errors",
    "NonRigidMarkerWarning": "_errors",
    "AmbiguousTreeWarning": "_errors",
    # data model and I/O
    "Trial": "io._trial",
    "bucket_size": "_math.padding",
    "load": "io._load",
    "load_sample": "io._sample",
    "sample_path": "io._sample",
    "save_trial": "io._load",
    # cleaning
    "clean": "clean._clean",
    "CleaningReport": "clean._clean",
    # skeleton from markers (Kirk et al. 2005)
    "segment_markers": "segment._spectral",
    "Segmentation": "segment._spectral",
    "joint_costs": "joints._topology",
    "fit_topology": "joints._topology",
    "Topology": "joints._topology",
    "UntestedJoint": "joints._topology",
    "untested_joints": "joints._topology",
    "PoseExchange": "joints._pose_check",
    "Attachment": "joints._attachments",
    "NearTie": "joints._near_ties",
    "near_ties": "joints._near_ties",
    "UndeterminedJoint": "joints._determination",
    "undetermined_joints": "joints._determination",
    "joint_resolution": "joints._determination",
    "bone_uncertainty": "joints._determination",
    "lowpass_markers": "clean._lowpass",
    "Lowpassed": "clean._lowpass",
    "solve_joint": "joints._cost",
    "solve_joints": "joints._cost",
    "JointSolution": "joints._cost",
    "fit_skeleton": "pipeline._fit",
    "SkeletonResult": "pipeline._fit",
    "load_result": "result._format",
    # rigid skeleton, IK and exports
    "fit_rigid": "skeleton._rigid_fit",
    "Skeleton": "skeleton._rigid_fit",
    "inverse_kinematics": "skeleton._ik",
    "Motion": "skeleton._ik",
    "forward_kinematics": "skeleton._ik",
    "ik_solve": "skeleton._ik",
    "BvhData": "result._bvh",
    "export_bvh": "result._bvh",
    "read_bvh": "result._bvh",
    # passive-marker correspondence
    "merge_labels": "relabel._merge",
    "LabelMapping": "relabel._merge",
    "needs_merging": "relabel._merge",
    "confirm_merges": "relabel._confirm",
    # Sar Dessai et al. 2006
    "normalize": "sd06._normalize",
    "Normalization": "sd06._normalize",
    "parameterize": "sd06._parameterize",
    "Parameterization": "sd06._parameterize",
    "Pose": "sd06._parameterize",
    "normalize_arrays": "sd06._normalize",
    "parameterize_arrays": "sd06._parameterize",
    "plot_joint_spheres": "plots._parameter_plots",
    "plot_speed_histograms": "plots._parameter_plots",
    "plot_angles": "plots._parameter_plots",
    "plot_summary": "plots._summary_plots",
    "plot_distance_std": "plots._summary_plots",
    "plot_spectrum": "plots._summary_plots",
    "plot_joint_costs": "plots._summary_plots",
    "plot_skeleton_3d": "plots._summary_plots",
    "plot_residuals": "plots._summary_plots",
    "plot_tree": "plots._summary_plots",
    # many trials
    "fit_batch": "pipeline._batch",
    "BatchResult": "pipeline._batch",
    "TrialOutcome": "pipeline._batch",
    "bone_length": "pipeline._batch_io",
    "plot_bone_lengths": "pipeline._batch_io",
    # learning-pipeline API (pure, jit/vmap/grad-able)
    "SkeletonStructure": "learn._functional",
    "RigidFit": "learn._functional",
    "joint_cost_fn": "learn._functional",
    "rigid_fit_fn": "learn._functional",
    "ik_fn": "learn._functional",
}

__all__ = sorted([*_LAZY, "synth", "__version__"])


def __getattr__(name: str) -> Any:
    if name == "synth":
        return importlib.import_module(".synth", __name__)
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'jaxskel' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # pragma: no cover - for static tooling only
    from ._errors import *  # noqa: F403
    from .io._trial import Trial  # noqa: F401
