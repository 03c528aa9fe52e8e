"""Geometry stage: descriptors of a settled stack, as pure functions on exact solids.

``describe(history)`` computes every registered descriptor (``DESCRIPTORS``) of a stack
given as one :class:`Arrangement` per deposited batch.
"""

from typing import TYPE_CHECKING

from chipstack.core.lazy import lazy_package

if TYPE_CHECKING:
    from chipstack.core.arrangement import Arrangement, arrangements_from_stack
    from chipstack.geometry.describe import Description, describe
    from chipstack.geometry.descriptor_kinds import DESCRIPTORS

__all__ = ["Arrangement", "DESCRIPTORS", "Description", "arrangements_from_stack", "describe"]

# Imported on first use: every command-line start imports geometry.stage, hence this
# package, and these modules bring numpy, scipy and manifold3d.
lazy_package(
    __name__,
    {
        "Arrangement": "chipstack.core.arrangement",
        "arrangements_from_stack": "chipstack.core.arrangement",
        "DESCRIPTORS": "chipstack.geometry.descriptor_kinds",
        "Description": "chipstack.geometry.describe",
        "describe": "chipstack.geometry.describe",
    },
)
