"""Compare two jaxskel result files dataset by dataset and attribute by attribute.

    python bench/compare_results.py BEFORE.h5 AFTER.h5 [--ignore-attr-prefix time_]

Prints every dataset or attribute that differs (floats within rtol 1e-9, atol 1e-12; NaNs
equal), every name present in one file only, and a count. Exit status 1 when anything
differs. Used to check that a refactoring leaves the demo's result unchanged
(``jaxskel demo -o before`` on the old commit, ``-o after`` on the new one).
"""

from __future__ import annotations

import argparse
import sys

import h5py
import numpy as np


def compare(before: str, after: str, ignore_prefixes: tuple[str, ...] = ("time_", "created")) -> list[str]:
    """Lines describing each difference between the files (empty: identical)."""
    out: list[str] = []
    with h5py.File(before, "r") as a, h5py.File(after, "r") as b:

        def attrs(path: str) -> None:
            x, y = a[path].attrs, b[path].attrs
            for name in sorted(set(x) | set(y)):
                if name.startswith(ignore_prefixes):
                    continue
                if name not in x or name not in y:
                    out.append(f"attribute {path}@{name} only in {'after' if name not in x else 'before'}")
                elif str(x[name]) != str(y[name]):
                    out.append(f"attribute {path}@{name}: {str(x[name])[:80]} != {str(y[name])[:80]}")

        def walk(path: str) -> None:
            attrs(path)
            names = sorted(set(a[path].keys()) | set(b[path].keys()))
            for name in names:
                p = f"{path.rstrip('/')}/{name}"
                if p not in a or p not in b:
                    out.append(f"{p} only in {'after' if p not in a else 'before'}")
                    continue
                if isinstance(a[p], h5py.Group):
                    walk(p)
                    continue
                attrs(p)
                u, v = a[p][()], b[p][()]
                u, v = np.asarray(u), np.asarray(v)
                if u.shape != v.shape:
                    out.append(f"{p}: shape {u.shape} != {v.shape}")
                elif u.dtype.kind in "fc":
                    if not np.allclose(u, v, rtol=1e-9, atol=1e-12, equal_nan=True):
                        out.append(f"{p}: max difference {np.nanmax(np.abs(u - v)):.3g}")
                elif not np.array_equal(u, v):
                    out.append(f"{p}: values differ")

        walk("/")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("before")
    p.add_argument("after")
    p.add_argument("--ignore-attr-prefix", action="append", default=None,
                   help="attributes to skip (default: time_ and created, the stage timings and the date)")
    args = p.parse_args(argv)
    diffs = compare(args.before, args.after, tuple(args.ignore_attr_prefix or ["time_", "created"]))
    with h5py.File(args.before, "r") as f:
        n = sum(1 for _ in _datasets(f))
    print("\n".join(diffs))
    print(f"{n} datasets compared, {len(diffs)} differences")
    return 1 if diffs else 0


def _datasets(group):
    for item in group.values():
        if isinstance(item, h5py.Group):
            yield from _datasets(item)
        else:
            yield item


if __name__ == "__main__":
    sys.exit(main())
