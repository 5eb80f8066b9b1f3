"""Exceptions raised by qpctl.

Every error the library raises on purpose derives from :class:`QpctlError`, so a caller can catch
one type; the command line turns any of them into a one-line message and a non-zero exit.
"""

from __future__ import annotations

from typing import Any


class QpctlError(Exception):
    """Base class of every error qpctl raises on purpose."""


class ConfigError(QpctlError, ValueError):
    """A scenario file, a ``--set`` override or a constructor argument is invalid.

    ``source`` names the file (or "--set", or the class) and ``key`` the dotted key at fault.
    """

    def __init__(self, message: str, *, source: str | None = None, key: str | None = None) -> None:
        self.source = source
        self.key = key
        self.message = message  # without the source and key
        where = ""
        if source and key:
            where = f"{source}: {key}: "
        elif source:
            where = f"{source}: "
        elif key:
            where = f"{key}: "
        super().__init__(where + message)


class InvalidStateError(QpctlError, ValueError):
    """A joint state or time handed to a controller is NaN/inf or wrongly shaped."""


class UnknownFrameError(QpctlError, KeyError):
    """A frame name does not exist in the robot model; the message lists those that do."""

    def __init__(self, name: str, available: list[str]) -> None:
        self.name = name
        self.available = list(available)
        super().__init__(f"unknown frame {name!r}; the model has: {', '.join(self.available)}")

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0])


class UnknownSolverError(QpctlError, ValueError):
    """A QP solver name is not installed or not known; the message lists the available ones."""

    def __init__(self, name: str, available: list[str]) -> None:
        self.name = name
        self.available = list(available)
        super().__init__(
            f"unknown or unavailable QP solver {name!r}; available: {', '.join(self.available)} "
            "(others can be installed with pip, e.g. `pip install qpsolvers[open_source_solvers]`)"
        )


class SolverError(QpctlError, RuntimeError):
    """The QP solver failed on a tick (numerical error, iteration limit, infeasibility); raised by a
    controller in strict mode (``QPController(..., strict=True)``) instead of falling back.

    ``problem`` holds the stacked QP (:class:`~qpctl.qp.Problem`), ``outcome`` the solve
    (:class:`~qpctl.outcome.SolveOutcome`: status, iterations, solver, x) and ``status`` the
    solver's own word, for debugging.
    """

    def __init__(self, message: str, *, status: str = "error", problem: Any = None, outcome: Any = None) -> None:
        self.status = status
        self.problem = problem
        self.outcome = outcome
        super().__init__(message)


class InfeasibleError(SolverError):
    """The QP has no solution that satisfies its hard constraints."""


class SimulationError(QpctlError, RuntimeError):
    """The simulated state diverged (non-finite state) or the integrator cannot go on."""


class PerceptionError(QpctlError, ValueError):
    """A sensor's input cannot be used: a wrongly shaped depth image, labels or point cloud, missing
    or invalid intrinsics, a camera pose that is not a rigid transform, a non-finite stamp, or stamps
    going backwards (:mod:`qpctl.perception`). Invalid *pixels* (NaN, inf, zero or negative depth) are
    not errors: they are dropped and counted."""


class ReplayError(QpctlError, RuntimeError):
    """A replay page cannot be written or shown: a run folder without what a replay needs (its
    ``trajectory.npz`` or the ``scenario.toml`` that ``qpctl simulate`` writes beside it), or no
    headless browser to render one (:mod:`qpctl.replay`)."""
