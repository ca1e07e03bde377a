"""jaxskel: automatic articulated skeletons from optical motion-capture markers, on JAX.

The flat public API lives here; the implementation is in small private modules
(``jaxskel.io._trial``, ``jaxskel.clean.clean._clean``, ...). Names are imported lazily so that
``import jaxskel`` stays fast and a command-line call pays only for what it uses.

Importing jaxskel changes no global state: no JAX setting, no environment variable, no
logging configuration. jaxskel computes in float64 (joint fitting needs it) by turning
JAX's 64-bit mode on only for the length of each of its own calls, in the calling
thread (``jaxskel._runtime.precision``); a float32 model in the same process stays
float32, and the pure functions (``jaxskel.learn``, ...) compute in float32 inside it.

On a CPU with few cores, start a process that fits with XLA's single-threaded Eigen,
``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false``, set before JAX's first computation:
with the multi-threaded pool, batched LAPACK kernels (the rigid fit's) were seen to
wedge for good on 2-core machines under load (``jaxskel._math.linalg``, docs/limits.md).
The ``jaxskel`` command sets it for its own process.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from ._version import __version__  # noqa: F401  (public: jaxskel.__version__)

# public name -> the part of jaxskel that defines it
_LAZY = {
    # errors and warnings
    "JaxskelError": "_errors",
    "InputError": "_errors",
    "DegenerateMotionError": "_errors",
    "SchemaError": "_errors",
    "ConvergenceWarning": "_errors",
    "UnitsWarning": "_errors",
    "TrackingWarning": "_errors",
    "DegenerateMotionWarning": "_errors",
    "NonRigidMarkerWarning": "_errors",
    "AmbiguousTreeWarning": "_errors",
    # recordings
    "Trial": "io",
    "load": "io",
    "save_trial": "io",
    "load_sample": "io",
    # the pipeline and its result
    "fit_skeleton": "pipeline",
    "fit_batch": "pipeline",
    "track": "pipeline",
    "TrackedTrial": "result",
    "FitOptions": "pipeline",
    "CleanOptions": "pipeline",
    "LabelOptions": "pipeline",
    "SegmentOptions": "pipeline",
    "JointOptions": "pipeline",
    "SkeletonOptions": "pipeline",
    "MotionOptions": "pipeline",
    "BodyOptions": "pipeline",
    "BatchResult": "pipeline",
    "TrialOutcome": "pipeline",
    "SkeletonResult": "result",
    "load_result": "result",
    "load_skeleton": "result",
    "export_osim": "result",
    # a process's compiled programs on disk (opt-in; the jaxskel command turns it on)
    "enable_compile_cache": "_runtime.compile_cache",
}

#: The stages, each a namespace of its own: ``jaxskel.segment.segment_markers``, ...
_SUBPACKAGES = ("io", "clean", "segment", "joints", "skeleton", "relabel", "sd06", "anatomy", "result", "plots",
                "pipeline", "learn", "synth")

__all__ = sorted([*_LAZY, *_SUBPACKAGES, "__version__"])


def __getattr__(name: str) -> Any:
    if name in _SUBPACKAGES:
        return importlib.import_module(f".{name}", __name__)
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'jaxskel' has no attribute {name!r}{_where(name)}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def _where(name: str) -> str:
    """``"; it is jaxskel.<stage>.<name>"`` where a stage exports ``name``, else ``""``."""
    if name.startswith("_"):  # a probe (IPython, pickle, ...) must not import every stage
        return ""
    for sub in _SUBPACKAGES:
        if name in getattr(importlib.import_module(f".{sub}", __name__), "__all__", ()):
            return f"; it is jaxskel.{sub}.{name}"
    return ""


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # pragma: no cover - for static tooling only
    from ._errors import *  # noqa: F403
    from .io import Trial  # noqa: F401
