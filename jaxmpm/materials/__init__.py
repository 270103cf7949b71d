"""Constitutive models, one module each, registered by the `model` name used in scene files;
`driver.drive` runs one of them at a single material point (the element test)."""

from jaxmpm.materials.base import material_parameters
from jaxmpm.materials.drucker_prager import DruckerPrager
from jaxmpm.materials.linear_elastic import LinearElastic

MODELS = {cls.model: cls for cls in (LinearElastic, DruckerPrager)}

__all__ = ["MODELS", "DruckerPrager", "LinearElastic", "material_parameters"]
