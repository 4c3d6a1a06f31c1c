"""Motions out to the animators' tools: `bvh(trajectory, figure, path)` writes a figure's
motion as a BVH file (Blender, Maya, MotionBuilder, game engines); `usd(trajectory, body,
path)` writes any body's as USD (the `usd` extra: usd-core). A figure's trajectory needs its
positions (`simulate(..., positions=True)`, `Task.simulate(..., positions=True)`); from the
command line, `python -m jaxmotion export RESULTS --format bvh|usd`.

These are the library's only functions that write files, and only to the path given.
"""

from ._export.bvh import bvh as bvh
from ._export.usd import usd as usd

__all__ = ["bvh", "usd"]
