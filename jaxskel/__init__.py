"""jaxskel: automatic articulated skeletons from optical motion-capture markers, on JAX.

The flat public API lives here; the implementation is in small private modules
(``jaxskel._trial``, ``jaxskel._clean``, ...). Names are imported lazily so that
``import jaxskel`` stays fast and a command-line call pays only for what it uses.

jaxskel enables JAX's 64-bit mode on import (joint fitting needs float64 accuracy;
arrays passed as float32 still compute in float32). Set ``JAXSKEL_NO_X64=1`` before
importing to leave JAX's global setting alone.

jaxskel also runs XLA's CPU backend with single-threaded Eigen
(``--xla_cpu_multi_thread_eigen=false`` in ``XLA_FLAGS``) unless ``XLA_FLAGS``
already says otherwise or ``JAXSKEL_XLA_MULTI_THREAD=1``: with the multi-threaded
Eigen pool, vmapped solves were seen to wedge for good on 2-core machines under
load (see ``jaxskel._linalg`` for the mechanism, and ``docs/design.md``). This only
takes effect if no JAX computation ran before ``import jaxskel``.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

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
    "Trial": "_trial",
    "bucket_size": "_padding",
    "load": "_io",
    "load_sample": "_data",
    "sample_path": "_data",
    "save_trial": "_io",
    # cleaning
    "clean": "_clean",
    "CleaningReport": "_clean",
    # skeleton from markers (Kirk et al. 2005)
    "segment_markers": "_segment",
    "Segmentation": "_segment",
    "joint_costs": "_topology",
    "fit_topology": "_topology",
    "Topology": "_topology",
    "UntestedJoint": "_topology",
    "untested_joints": "_topology",
    "PoseExchange": "_pose_check",
    "Attachment": "_attachments",
    "NearTie": "_near_ties",
    "near_ties": "_near_ties",
    "UndeterminedJoint": "_determination",
    "undetermined_joints": "_determination",
    "joint_resolution": "_determination",
    "bone_uncertainty": "_determination",
    "lowpass_markers": "_lowpass",
    "Lowpassed": "_lowpass",
    "solve_joint": "_jointcost",
    "solve_joints": "_jointcost",
    "JointSolution": "_jointcost",
    "fit_skeleton": "_fit",
    "SkeletonResult": "_fit",
    "load_result": "_result_io",
    # rigid skeleton, IK and exports
    "fit_rigid": "_rigid",
    "Skeleton": "_rigid",
    "inverse_kinematics": "_ik",
    "Motion": "_ik",
    "forward_kinematics": "_ik",
    "ik_solve": "_ik",
    "BvhData": "_bvh",
    "export_bvh": "_bvh",
    "read_bvh": "_bvh",
    # passive-marker correspondence
    "merge_labels": "_relabel",
    "LabelMapping": "_relabel",
    "needs_merging": "_relabel",
    "confirm_merges": "_relabel_confirm",
    # Sar Dessai et al. 2006
    "normalize": "_normalize",
    "Normalization": "_normalize",
    "parameterize": "_parameterize",
    "Parameterization": "_parameterize",
    "Pose": "_parameterize",
    "normalize_arrays": "_normalize",
    "parameterize_arrays": "_parameterize",
    "plot_joint_spheres": "_plots_params",
    "plot_speed_histograms": "_plots_params",
    "plot_angles": "_plots_params",
    "plot_summary": "_plots",
    "plot_distance_std": "_plots",
    "plot_spectrum": "_plots",
    "plot_joint_costs": "_plots",
    "plot_skeleton_3d": "_plots",
    "plot_residuals": "_plots",
    "plot_tree": "_plots",
    # many trials
    "fit_batch": "_batch",
    "BatchResult": "_batch",
    "TrialOutcome": "_batch",
    "bone_length": "_batch_io",
    "plot_bone_lengths": "_batch_io",
    # learning-pipeline API (pure, jit/vmap/grad-able)
    "SkeletonStructure": "_functional",
    "RigidFit": "_functional",
    "joint_cost_fn": "_functional",
    "rigid_fit_fn": "_functional",
    "ik_fn": "_functional",
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
    from ._trial import Trial  # noqa: F401
