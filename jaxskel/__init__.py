"""jaxskel: automatic articulated skeletons from optical motion-capture markers, on JAX.

The flat public API lives here; the implementation is in small private modules
(``jaxskel.io._trial``, ``jaxskel.clean.clean._clean``, ...). Names are imported lazily so that
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

# public name -> the part of jaxskel that defines it
_LAZY = {
    # errors and warnings
    "JaxskelError": "_errors",
    "InputError": "_errors",
    "DegenerateMotionError": "_errors",
    "SchemaError": "_errors",
    "ConvergenceWarning": "_errors",
    "UnitsWarning": "_errors",
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
    "FitOptions": "pipeline",
    "CleanOptions": "pipeline",
    "LabelOptions": "pipeline",
    "SegmentOptions": "pipeline",
    "JointOptions": "pipeline",
    "SkeletonOptions": "pipeline",
    "MotionOptions": "pipeline",
    "BatchResult": "pipeline",
    "TrialOutcome": "pipeline",
    "SkeletonResult": "result",
    "load_result": "result",
}

#: The stages, each a namespace of its own: ``jaxskel.segment.segment_markers``, ...
_SUBPACKAGES = ("io", "clean", "segment", "joints", "skeleton", "relabel", "sd06", "result", "plots", "pipeline",
                "learn", "synth")

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
