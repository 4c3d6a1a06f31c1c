"""jaxmotion: automatic motion synthesis for animated characters, in JAX.

Bodies (mass-spring lattices, articulated figures), controllers with a handful of
parameters, objectives that score a motion, and stochastic searches that find good
parameters; the simulator runs on diffrax, vectorised with `vmap` and differentiable.
Fitness is always maximised.
"""

from . import checks as checks
from . import export as export
from . import figures as figures
from . import lattices as lattices
from ._body.base import AbstractBody as AbstractBody
from ._body.base import AbstractDynamics as AbstractDynamics
from ._body.base import BodyState as BodyState
from ._body.figure import Figure as Figure
from ._body.figure import FigurePositions as FigurePositions
from ._body.figure import FigureVelocities as FigureVelocities
from ._body.lattice import Lattice as Lattice
from ._composite import Composite as Composite
from ._control.base import AbstractController as AbstractController
from ._control.base import AbstractControllerSpace as AbstractControllerSpace
from ._control.base import ControllerState as ControllerState
from ._control.deformations import REFLEX_NAMES as REFLEX_NAMES
from ._control.deformations import deform as deform
from ._control.regimes import PERTURBATIONS as PERTURBATIONS
from ._control.regimes import Regimes as Regimes
from ._control.regimes import RegimesSpace as RegimesSpace
from ._control.sense_bsr import BSRState as BSRState
from ._control.sense_bsr import SenseBSR as SenseBSR
from ._control.sense_bsr import SenseBSRSpace as SenseBSRSpace
from ._control.sequence import Sequence as Sequence
from ._control.sequence import SequenceState as SequenceState
from ._control.spring_net import MUTATION_KINDS as MUTATION_KINDS
from ._control.spring_net import MUTATION_PROBABILITIES as MUTATION_PROBABILITIES
from ._control.spring_net import SpringNet as SpringNet
from ._control.spring_net import SpringNetSpace as SpringNetSpace
from ._control.spring_net import spring_pairs as spring_pairs
from ._control.time_bsr import TimeBSR as TimeBSR
from ._control.time_bsr import TimeBSRSpace as TimeBSRSpace
from ._devices import use_cpu_cores as use_cpu_cores
from ._objective import terms as _builtin_terms  # noqa: F401  (registers the built-in terms)
from ._objective.registry import Objective as Objective
from ._objective.registry import register_term as register_term
from ._objective.registry import terms as objective_terms
from ._objective.script import Script as Script
from ._objective.script import ScriptError as ScriptError
from ._objective.script import closeness as closeness
from ._objective.script import script_measures as script_measures
from ._search.evolve import Evolve as Evolve
from ._search.evolve import EvolveState as EvolveState
from ._search.evolve import evolve as evolve
from ._search.evosax import Evosax as Evosax
from ._search.evosax import EvosaxState as EvosaxState
from ._search.hill_climb import HillClimbState as HillClimbState
from ._search.hill_climb import ParallelHillClimb as ParallelHillClimb
from ._search.hill_climb import SearchResult as SearchResult
from ._search.hill_climb import parallel_hill_climb as parallel_hill_climb
from ._search.history import History as History
from ._search.protocol import SEARCHERS as SEARCHERS
from ._search.protocol import AbstractSearcher as AbstractSearcher
from ._search.protocol import drive as drive
from ._search.protocol import fittest as fittest
from ._search.protocol import register as register_searcher
from ._search.refine import RefineHistory as RefineHistory
from ._search.refine import RefineResult as RefineResult
from ._search.refine import Smoothing as Smoothing
from ._search.refine import fitness_and_gradient as fitness_and_gradient
from ._search.refine import gradient_cost as gradient_cost
from ._search.refine import refine as refine
from ._search.serial import SerialSearch as SerialSearch
from ._search.serial import SerialSearchResult as SerialSearchResult
from ._search.serial import SerialSearchState as SerialSearchState
from ._search.serial import serial_search as serial_search
from ._search.transitions import TransitionSearch as TransitionSearch
from ._search.transitions import TransitionSearchResult as TransitionSearchResult
from ._search.transitions import TransitionSearchState as TransitionSearchState
from ._search.transitions import transition_search as transition_search
from ._sim.robust import Robustness as Robustness
from ._sim.simulate import simulate as simulate
from ._sim.trajectory import Observation as Observation
from ._sim.trajectory import SimulationState as SimulationState
from ._sim.trajectory import Trajectory as Trajectory
from ._task import Task as Task
from ._world import World as World
from ._world import floor_force as floor_force

__version__ = "0.1.0"


def __getattr__(name):
    # `jm.viz` is imported on first use, so `import jaxmotion` does not load matplotlib.
    if name == "viz":
        import importlib

        return importlib.import_module(".viz", __name__)
    raise AttributeError(f"module 'jaxmotion' has no attribute {name!r}")


__all__ = [
    "MUTATION_KINDS",
    "MUTATION_PROBABILITIES",
    "PERTURBATIONS",
    "REFLEX_NAMES",
    "SEARCHERS",
    "AbstractBody",
    "AbstractController",
    "AbstractControllerSpace",
    "AbstractDynamics",
    "AbstractSearcher",
    "BSRState",
    "BodyState",
    "Composite",
    "ControllerState",
    "Evolve",
    "EvolveState",
    "Evosax",
    "EvosaxState",
    "Figure",
    "FigurePositions",
    "FigureVelocities",
    "HillClimbState",
    "History",
    "Lattice",
    "Objective",
    "Observation",
    "ParallelHillClimb",
    "RefineHistory",
    "RefineResult",
    "Regimes",
    "RegimesSpace",
    "Robustness",
    "Script",
    "ScriptError",
    "SearchResult",
    "SenseBSR",
    "SenseBSRSpace",
    "Sequence",
    "SequenceState",
    "SerialSearch",
    "SerialSearchResult",
    "SerialSearchState",
    "SimulationState",
    "Smoothing",
    "SpringNet",
    "SpringNetSpace",
    "Task",
    "TimeBSR",
    "TimeBSRSpace",
    "Trajectory",
    "TransitionSearch",
    "TransitionSearchResult",
    "TransitionSearchState",
    "World",
    "checks",
    "closeness",
    "deform",
    "drive",
    "evolve",
    "export",
    "figures",
    "fitness_and_gradient",
    "fittest",
    "floor_force",
    "gradient_cost",
    "lattices",
    "objective_terms",
    "parallel_hill_climb",
    "refine",
    "register_searcher",
    "register_term",
    "script_measures",
    "serial_search",
    "simulate",
    "spring_pairs",
    "transition_search",
    "use_cpu_cores",
    "viz",
]
