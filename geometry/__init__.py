"""Geometry stage: descriptors of a settled stack, as pure functions on exact solids."""
