"""`Trial`: one motion-capture recording, the data contract of every stage.

A trial holds marker positions of shape (F, M, 3) in metres with NaN where a
marker is missing, the marker labels, the frame rate and where it came from.
It is immutable: every operation returns a new trial and the caller's arrays
are never written to.

Traced (JAX) code never sees NaN: :meth:`Trial.to_arrays` hands it ``(x, mask)``
with missing entries zeroed, and :meth:`Trial.padded` pads both to bucket sizes
so that one compiled function serves recordings of many lengths.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import InputError
from .._math.padding import bucket_size
from .._math.rotation import skew_np
from ._bounds import MAX_LABEL_CHARS
from ._raw import UP_AXES

__all__ = ["Trial", "UP_AXES", "rotation_between_axes"]

#: Axis names accepted for :attr:`Trial.up_axis` ("unknown" when a file does not say).

_AXIS_VECTORS = {
    "x": (1.0, 0.0, 0.0),
    "y": (0.0, 1.0, 0.0),
    "z": (0.0, 0.0, 1.0),
    "-x": (-1.0, 0.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "-z": (0.0, 0.0, -1.0),
}


def rotation_between_axes(src: str, dst: str) -> np.ndarray:
    """Proper rotation matrix R (3, 3) with ``R @ e_src = e_dst``.

    Both are axis names from :data:`UP_AXES` (not "unknown"). For opposite axes
    the rotation is a half turn about the first coordinate axis orthogonal to them.
    """
    for name in (src, dst):
        if name not in _AXIS_VECTORS:
            raise InputError(f"unknown axis {name!r}; use one of {UP_AXES[:-1]}")
    a = np.asarray(_AXIS_VECTORS[src])
    b = np.asarray(_AXIS_VECTORS[dst])
    c = float(a @ b)
    if c > 0.5:
        return np.eye(3)
    if c < -0.5:
        # Half turn about an axis orthogonal to a: R = 2 n n^T - I.
        n = np.eye(3)[int(np.argmin(np.abs(a)))]
        return 2.0 * np.outer(n, n) - np.eye(3)
    # Quarter turn about k = a x b: Rodrigues with sin = 1 and cos = 0 exactly, so the
    # matrix permutes coordinates exactly (cos(pi / 2) in floating point is 6e-17).
    kx = skew_np(np.cross(a, b))
    return np.eye(3) + kx + kx @ kx


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Trial:
    """One recording: marker positions (F, M, 3) in metres, NaN where missing.

    Parameters
    ----------
    positions
        Array (F, M, 3): F frames, M markers, metres. NaN (any coordinate) marks
        a missing sample; the whole sample is then treated as missing.
    labels
        M unique marker labels, of at most 1024 characters each.
    rate
        Frame rate in Hz (> 0).
    up_axis
        The recording's vertical axis, one of :data:`UP_AXES`.
    source
        Where the data came from (file path or a description).
    metadata
        Free-form, read-only provenance (reader, original units, first frame, ...).
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    rate: float
    up_axis: str = "unknown"
    source: str = ""
    metadata: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        pos = np.asarray(self.positions)
        if pos.ndim != 3 or pos.shape[-1] != 3:
            raise InputError(
                f"Trial positions must have shape (frames, markers, 3); got {pos.shape}"
                f"{' from ' + self.source if self.source else ''}."
            )
        if not np.issubdtype(pos.dtype, np.floating):
            pos = pos.astype(np.float64)
        if np.isinf(pos).any():
            raise InputError(
                "Trial positions contain infinite values; mark missing samples with NaN instead."
            )
        # A sample is missing as a whole: one NaN coordinate blanks all three.
        missing = np.isnan(pos).any(axis=-1)
        if missing.any() and not np.isnan(pos[missing]).all():
            pos = pos.copy()
            pos[missing] = np.nan
        labels = tuple(str(lab) for lab in self.labels)
        if len(labels) != pos.shape[1]:
            raise InputError(
                f"Trial has {pos.shape[1]} markers but {len(labels)} labels; give one label per marker."
            )
        long = next((i for i, lab in enumerate(labels) if len(lab) > MAX_LABEL_CHARS), None)
        if long is not None:
            raise InputError(
                f"marker label {long + 1} ({labels[long][:20]!r}...) is {len(labels[long])} characters long; "
                f"labels have at most {MAX_LABEL_CHARS} (every stage copies them into arrays as wide as the longest)"
            )
        if len(set(labels)) != len(labels):
            dup = sorted({lab for lab in labels if labels.count(lab) > 1})
            raise InputError(f"marker labels must be unique; duplicated: {dup[:10]}")
        try:
            rate = float(self.rate)
        except (TypeError, ValueError):
            raise InputError(f"frame rate must be a number, got {self.rate!r}") from None
        if not np.isfinite(rate) or rate <= 0:
            raise InputError(f"frame rate must be a positive number of Hz, got {self.rate!r}")
        if self.up_axis not in UP_AXES:
            raise InputError(f"up_axis must be one of {UP_AXES}, got {self.up_axis!r}")
        object.__setattr__(self, "positions", _readonly(pos))
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate", rate)
        object.__setattr__(self, "metadata", types.MappingProxyType(dict(self.metadata)))

    # ------------------------------------------------------------------ sizes
    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    @property
    def duration(self) -> float:
        """Length in seconds (``n_frames / rate``)."""
        return self.n_frames / self.rate

    @property
    def times(self) -> np.ndarray:
        """Frame times in seconds from 0, shape (F,)."""
        return np.arange(self.n_frames) / self.rate

    @property
    def mask(self) -> np.ndarray:
        """(F, M) bool, True where a marker is present."""
        return ~np.isnan(self.positions[..., 0])

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        present = self.mask.mean() * 100 if self.positions.size else 0.0
        src = f", source={self.source!r}" if self.source else ""
        return (
            f"Trial({self.n_frames} frames x {self.n_markers} markers @ {self.rate:g} Hz, "
            f"{self.duration:.2f} s, {present:.1f}% present, up={self.up_axis}{src})"
        )

    # -------------------------------------------------------------- selection
    def replace(self, **changes: Any) -> Trial:
        """A copy with some fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    def marker_index(self, labels: str | Iterable[str | int]) -> np.ndarray:
        """Indices of the given labels (or pass-through integer indices)."""
        if isinstance(labels, str):
            labels = [labels]
        lookup = {lab: i for i, lab in enumerate(self.labels)}
        out = []
        for lab in labels:
            if isinstance(lab, (int, np.integer)):
                if not -self.n_markers <= int(lab) < self.n_markers:
                    raise InputError(f"marker index {lab} out of range for {self.n_markers} markers")
                out.append(int(lab) % self.n_markers)
            elif lab in lookup:
                out.append(lookup[lab])
            else:
                raise InputError(
                    f"no marker labelled {lab!r}; available: {', '.join(self.labels[:20])}"
                    f"{' ...' if self.n_markers > 20 else ''}"
                )
        return np.asarray(out, dtype=int)

    def select_markers(self, markers: str | Sequence[str | int] | np.ndarray) -> Trial:
        """Trial restricted to some markers (labels, indices or a boolean mask), in the given order."""
        arr = np.asarray(markers)
        if arr.dtype == bool:
            if arr.shape != (self.n_markers,):
                raise InputError(f"boolean marker mask must have shape ({self.n_markers},)")
            idx = np.flatnonzero(arr)
        else:
            idx = self.marker_index(markers if not isinstance(markers, np.ndarray) else list(markers))
        return self.replace(
            positions=self.positions[:, idx], labels=tuple(self.labels[i] for i in idx)
        )

    def drop_markers(self, markers: str | Sequence[str | int]) -> Trial:
        """Trial without the given markers."""
        drop = set(self.marker_index(markers).tolist())
        return self.select_markers([i for i in range(self.n_markers) if i not in drop])

    def select_frames(self, frames: slice | Sequence[int] | np.ndarray) -> Trial:
        """Trial restricted to some frames (a slice, indices or a boolean mask).

        A trial concatenated from several recordings keeps ``metadata["trial_bounds"]``
        true: the ranges are recomputed over the selected frames (one per run of frames
        from one recording), and dropped when all come from one recording.
        """
        if isinstance(frames, slice):
            index = np.arange(self.n_frames)[frames]
        else:
            arr = np.asarray(frames)
            if arr.dtype == bool and arr.shape != (self.n_frames,):
                raise InputError(f"boolean frame mask must have shape ({self.n_frames},)")
            index = np.arange(self.n_frames)[arr]
        metadata = dict(self.metadata)
        if "trial_bounds" in metadata:
            stops = np.array([hi for _, hi in metadata.pop("trial_bounds")])
            piece = np.searchsorted(stops, index, side="right")
            cuts = np.flatnonzero(np.diff(piece) != 0) + 1
            if cuts.size:
                edges = np.concatenate([[0], cuts, [index.size]]).tolist()
                metadata["trial_bounds"] = tuple(zip(edges[:-1], edges[1:]))
        return self.replace(positions=self.positions[index], metadata=metadata)

    def __getitem__(self, frames: slice | Sequence[int] | np.ndarray) -> Trial:
        """``trial[a:b]`` selects frames, like :meth:`select_frames`."""
        return self.select_frames(frames)

    def between(self, start_s: float, stop_s: float) -> Trial:
        """Frames with ``start_s <= t < stop_s`` seconds."""
        t = self.times
        return self.select_frames((t >= start_s) & (t < stop_s))

    # ------------------------------------------------------------ conversions
    def to_arrays(self, dtype: Any = np.float64) -> tuple[np.ndarray, np.ndarray]:
        """``(x, mask)``: x (F, M, 3) with missing samples zeroed, mask (F, M) bool.

        This is the form every JAX function in jaxskel takes: no NaN enters traced code.
        """
        mask = self.mask
        x = np.where(mask[..., None], self.positions, 0.0).astype(dtype)
        return x, mask

    def padded(
        self,
        n_frames: int | None = None,
        n_markers: int | None = None,
        dtype: Any = np.float64,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(x, mask)`` padded with absent samples to (n_frames, n_markers).

        By default both sizes are rounded up by :func:`jaxskel._math.padding.bucket_size`, so
        recordings of similar size share one compiled shape.
        """
        f = bucket_size(self.n_frames) if n_frames is None else int(n_frames)
        m = bucket_size(self.n_markers, minimum=8) if n_markers is None else int(n_markers)
        if f < self.n_frames or m < self.n_markers:
            raise InputError(
                f"cannot pad a {self.n_frames}x{self.n_markers} trial down to {f}x{m}"
            )
        x, mask = self.to_arrays(dtype)
        xp = np.zeros((f, m, 3), dtype=dtype)
        mp = np.zeros((f, m), dtype=bool)
        xp[: self.n_frames, : self.n_markers] = x
        mp[: self.n_frames, : self.n_markers] = mask
        return xp, mp

    def to_up_axis(self, up: str = "z") -> Trial:
        """The same motion rotated so that this trial's up axis becomes ``up``.

        A proper rotation (no mirroring), so handedness and skeletons are preserved.
        """
        if self.up_axis == "unknown":
            raise InputError(
                "this trial's up axis is unknown; set it first with trial.replace(up_axis='y') "
                "(or 'z', '-z', ...) and then convert"
            )
        rot = rotation_between_axes(self.up_axis, up)
        return self.transformed(rot).replace(up_axis=up)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray | None = None) -> Trial:
        """Positions mapped by ``x -> R x + t`` (R (3, 3), t (3,)); NaN stays NaN.

        The up axis is kept: for a general rotation it no longer names a coordinate
        axis, so callers that care should set it themselves.
        """
        rot = np.asarray(rotation, dtype=float)
        if rot.shape != (3, 3):
            raise InputError(f"rotation must be 3x3, got {rot.shape}")
        t = np.zeros(3) if translation is None else np.asarray(translation, dtype=float)
        return self.replace(positions=self.positions @ rot.T + t)

    # --------------------------------------------------------------------- io
    def save(self, path: str, *, overwrite: bool = False) -> None:
        """Write this trial to HDF5 (``.h5``), C3D (``.c3d``) or TRC (``.trc``) by suffix.

        The write is atomic (temporary file, then rename). An existing file is
        only replaced with ``overwrite=True``.
        """
        file = Path(path)
        suffix = file.suffix.lower()
        if suffix == ".c3d":
            from ._c3d import write_c3d as write
        elif suffix == ".trc":
            from ._trc import write_trc as write
        elif suffix in (".h5", ".hdf5"):
            from ._h5 import write_h5 as write
        else:
            raise InputError(
                f"cannot write {file}: unknown file type {file.suffix!r}; supported: .c3d, .h5, .hdf5, .trc"
            )
        write(self, file, overwrite=overwrite)
