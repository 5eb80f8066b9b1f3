"""``python -m qpctl.native``: build the native library ahead of first use (``make env`` runs it);
prints where it is, or why it cannot be built (not an error: the Python path serves)."""

from qpctl.native import NativeBuildError, build

try:
    print(f"qpctl.native: {build()}")
except NativeBuildError as e:
    print(f"qpctl.native: not built ({e}); the brake rollout and the rigid-body pass run their Python paths")
