"""`python -m services.planner.native`: build the kernel (make does, at install)."""

from services.planner.native import build

print(build())
