"""Motion checks: `leap`, `somersault`, `pirouette`, each a function of a Trajectory that
returns a `CheckResult` (see each function for its thresholds)."""

from ._checks import CHECKS as CHECKS
from ._checks import CheckResult as CheckResult
from ._checks import leap as leap
from ._checks import pirouette as pirouette
from ._checks import somersault as somersault

__all__ = ["CHECKS", "CheckResult", "leap", "pirouette", "somersault"]
