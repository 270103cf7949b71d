"""Constitutive models, one module each, registered by the `model` name used in scene files."""

from jaxmpm.materials.base import material_parameters
from jaxmpm.materials.linear_elastic import LinearElastic

MODELS = {cls.model: cls for cls in (LinearElastic,)}

__all__ = ["MODELS", "LinearElastic", "material_parameters"]
