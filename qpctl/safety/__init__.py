"""Stop before contact (issue 22): brakes that bring the arm to rest within its drives' limits, the
oracle that certifies a state viable by exhibiting one (:mod:`qpctl.safety.oracle`), and the verified
backup that applies a controller's torque only when a brake from its successor state is verified
(:mod:`qpctl.safety.backup`)."""

from qpctl.safety.backup import BackupGuard
from qpctl.safety.oracle import BRAKE_GAINS, Certificate, certify, rollout

__all__ = ["BRAKE_GAINS", "BackupGuard", "Certificate", "certify", "rollout"]
