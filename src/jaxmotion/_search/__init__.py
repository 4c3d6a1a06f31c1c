"""Searches. Importing the package registers every searcher (`protocol.SEARCHERS`)."""

from . import evolve as evolve
from . import evosax as evosax
from . import hill_climb as hill_climb
from . import serial as serial
