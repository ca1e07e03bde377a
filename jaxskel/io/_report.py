"""What loading a file changed about its markers, said in words.

:func:`jaxskel.load` records in a trial's metadata every point it dropped, every label
it renamed or kept whole, and every marker it kept without a single sample (the fit's
cleaning drops those). :func:`load_report` turns that record into lines a user reads
before a fit (``jaxskel fit``, ``jaxskel info``): nothing a file held disappears unsaid.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["load_report"]

# Labels shown per line; the rest are counted.
_SHOWN = 12


def load_report(metadata: Mapping[str, Any]) -> list[str]:
    """Lines saying what loading dropped, renamed or found empty, and why; ``[]`` if nothing.

    ``metadata`` is a loaded :class:`~jaxskel.Trial`'s (``trial.metadata``), read from
    its entries ``dropped_reasons``, ``renamed_labels``, ``label_prefixes``,
    ``kept_prefix_labels``, ``empty_labels`` and ``short_rows``.
    """
    lines = []
    dropped: Mapping[str, str] = metadata.get("dropped_reasons") or {}
    if dropped:
        by_reason: dict[str, list[str]] = {}
        for label, reason in dropped.items():
            by_reason.setdefault(reason, []).append(label)
        parts = [f"{_names(labels)} ({reason})" for reason, labels in by_reason.items()]
        lines.append(f"dropped {_count(len(dropped), 'point')}: {'; '.join(parts)}")
    renamed: Mapping[str, str] = metadata.get("renamed_labels") or {}
    if renamed:
        parts = [
            f"{old!r} -> {new} ({'blank label' if not old.split(' #')[0] else 'repeated label'})"
            for old, new in list(renamed.items())[:_SHOWN]
        ]
        more = f" and {len(renamed) - _SHOWN} more" if len(renamed) > _SHOWN else ""
        lines.append(f"renamed {_count(len(renamed), 'label')}: {', '.join(parts)}{more}")
    prefixes = list(metadata.get("label_prefixes") or [])
    kept = list(metadata.get("kept_prefix_labels") or [])
    if prefixes:
        shown = ", ".join(f"{p!r}" for p in prefixes[:_SHOWN])
        line = f"removed the subject prefix{'es' if len(prefixes) > 1 else ''} {shown} from the labels"
        if kept:
            line += f", except {_names(kept)} (removing it would give two markers one label)"
        lines.append(line)
    empty: Mapping[str, str] = metadata.get("empty_labels") or {}
    if empty:
        by_reason = {}
        for label, reason in empty.items():
            by_reason.setdefault(reason, []).append(label)
        parts = [f"{_names(labels)} ({reason})" for reason, labels in by_reason.items()]
        lines.append(f"{_count(len(empty), 'marker')} without a sample, dropped by the fit: {'; '.join(parts)}")
    short = int(metadata.get("short_rows") or 0)
    if short and not str(metadata.get("file", "")).lower().endswith((".h5", ".hdf5")):  # a saved trial has no rows
        lines.append(
            f"{_count(short, 'data row')} end{'s' if short == 1 else ''} before the last marker's columns "
            "(the markers past the end are missing in those frames)"
        )
    return lines


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _names(labels: list[str]) -> str:
    shown = ", ".join(labels[:_SHOWN])
    return shown + (f" and {len(labels) - _SHOWN} more" if len(labels) > _SHOWN else "")
