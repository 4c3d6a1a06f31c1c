"""Pictures of motions and searches, with matplotlib: the learning plot of a search, a 3D
animation of a trajectory (inline in Jupyter, or saved as GIF or MP4), a filmstrip of poses
and the twelve reflexes of a lattice; and the composite-motion editor for Jupyter
(`composite_editor`, the `editor` extra). Nothing here touches pyplot's global state; every
function returns its figure or animation.
"""

from ._viz.animation import Animation as Animation
from ._viz.animation import animate as animate
from ._viz.editor import CompositeEditor as CompositeEditor
from ._viz.editor import composite_editor as composite_editor
from ._viz.filmstrip import filmstrip as filmstrip
from ._viz.learning import learning_curves as learning_curves
from ._viz.learning import learning_plot as learning_plot
from ._viz.reflexes import reflexes as reflexes

__all__ = [
    "Animation",
    "CompositeEditor",
    "animate",
    "composite_editor",
    "filmstrip",
    "learning_curves",
    "learning_plot",
    "reflexes",
]
