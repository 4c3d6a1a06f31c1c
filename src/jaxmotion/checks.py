"""Motion checks: `leap`, `somersault`, `pirouette` (first paper) and `shuffle`,
`cartwheel`, `bound`, `jump`, `walk` (second paper), `hop`, `roll` and `hop_or_roll` (third
paper), each a function of a Trajectory that returns a
`CheckResult` (see each function for its thresholds), and `walk_turn_walk` (second paper, Rex), a
function of a sequence of three trajectories."""

from ._checks import CHECKS as CHECKS
from ._checks import FLIGHT_CLEARANCE as FLIGHT_CLEARANCE
from ._checks import FLIGHT_SECONDS as FLIGHT_SECONDS
from ._checks import CheckResult as CheckResult
from ._checks import bound as bound
from ._checks import cartwheel as cartwheel
from ._checks import flights as flights
from ._checks import hop as hop
from ._checks import hop_or_roll as hop_or_roll
from ._checks import jump as jump
from ._checks import leap as leap
from ._checks import pirouette as pirouette
from ._checks import roll as roll
from ._checks import shuffle as shuffle
from ._checks import somersault as somersault
from ._checks import steps as steps
from ._checks import walk as walk
from ._checks import walk_turn_walk as walk_turn_walk

__all__ = [
    "CHECKS",
    "FLIGHT_CLEARANCE",
    "FLIGHT_SECONDS",
    "CheckResult",
    "bound",
    "cartwheel",
    "flights",
    "hop",
    "hop_or_roll",
    "jump",
    "leap",
    "pirouette",
    "roll",
    "shuffle",
    "somersault",
    "steps",
    "walk",
    "walk_turn_walk",
]
