"""Builders of articulated figures: the second paper's characters `star_man`,
`beryl_biped`, `cujo`, `rex`, `bob`, and the third paper's `snake` and `luxo`; `Joint`
describes one joint angle."""

from ._body.figure import Joint as Joint
from ._body.figure_builders import beryl_biped as beryl_biped
from ._body.figure_builders import bob as bob
from ._body.figure_builders import cujo as cujo
from ._body.figure_builders import luxo as luxo
from ._body.figure_builders import rex as rex
from ._body.figure_builders import snake as snake
from ._body.figure_builders import star_man as star_man

__all__ = ["Joint", "beryl_biped", "bob", "cujo", "luxo", "rex", "snake", "star_man"]
