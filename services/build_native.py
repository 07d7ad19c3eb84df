"""`python -m services.build_native`: build every service's native kernels (make does, at
install). A library that cannot be built is reported; its service then uses the JAX form."""

from __future__ import annotations

import sys

from common.native import Library, NativeUnavailable
from services.planner import native as planner_native
from services.sensor import native as sensor_native

LIBRARIES: tuple[Library, ...] = (planner_native.LIBRARY, sensor_native.LIBRARY)


def main() -> int:
    failed = 0
    for library in LIBRARIES:
        try:
            print(library.build())
        except NativeUnavailable as e:
            failed += 1
            print(f"not built, its service uses the JAX form: {e}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
