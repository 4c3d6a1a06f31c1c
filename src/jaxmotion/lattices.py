"""Builders of mass-spring lattices: `cube`, `pyramid`, `chair` and `from_points`."""

from ._body.lattice_builders import chair as chair
from ._body.lattice_builders import cube as cube
from ._body.lattice_builders import from_points as from_points
from ._body.lattice_builders import pyramid as pyramid

__all__ = ["chair", "cube", "from_points", "pyramid"]
