"""The built-in descriptors, one module each, every module ending with its
``DESCRIPTOR`` (:class:`geometry.descriptors.base.Descriptor`); the registry
(:mod:`geometry.descriptor_kinds`) names each by ``"module:DESCRIPTOR"``."""
