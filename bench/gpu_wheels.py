"""Pick which carried wheels to install on a machine that cannot reach a package index.

    python3 bench/gpu_wheels.py WHEEL_DIR      # prints the wheel paths to install, one a line

A carried wheel is chosen when its distribution is missing there or installed in an
older version than the wheel (a newer installed one is left alone: it was installed
together with that machine's jax). Reports each decision on stderr.
"""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

from packaging.utils import canonicalize_name, parse_wheel_filename
from packaging.version import Version


def main() -> None:
    for wheel in sorted(Path(sys.argv[1]).glob("*.whl")):
        name, version, _, _ = parse_wheel_filename(wheel.name)
        try:
            have = Version(metadata.version(name))
        except metadata.PackageNotFoundError:
            have = None
        take = have is None or have < version
        print(f"{canonicalize_name(name)}: installed {have}, carried {version} -> "
              f"{'carried' if take else 'installed'}", file=sys.stderr)
        if take:
            print(wheel)


if __name__ == "__main__":
    main()
