"""Geometry stage: descriptors of a settled stack, as pure functions on exact solids.

``describe(history)`` computes every registered descriptor (``DESCRIPTORS``) of a stack
given as one :class:`Arrangement` per deposited batch.
"""

from geometry.arrangement import Arrangement, arrangements_from_stack
from geometry.describe import DESCRIPTORS, Description, describe

__all__ = ["Arrangement", "DESCRIPTORS", "Description", "arrangements_from_stack", "describe"]
