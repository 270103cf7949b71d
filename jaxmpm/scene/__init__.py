"""Scenes: the TOML scene format, read into frozen dataclasses and checked before compiling.

- `parts`: the dataclasses a scene is made of (`Grid`, `Body`, ...), the presets, the words;
- `schema`: every key of the file once (kind, unit, default, range, meaning);
- `files`: TOML <-> dicts <-> the parts, read through the schema; `with_value`'s dict;
- `checks`: the schema's checks on any scene, and those that relate keys;
- `model`: `Scene` itself, built from the parts, checked, converted; `load_scene`;
- `reference`: docs/scene_reference.md, generated from the schema.
"""

from jaxmpm.scene.files import read_material, scene_to_dict
from jaxmpm.scene.model import Scene, load_scene, scene_from_dict
from jaxmpm.scene.parts import (
    BOUNDARY_KINDS, DEFAULT_PRESET, GEOMETRIES, KINEMATICS, NAME, NUMERICS_CHOICES, PRESETS, PROBE_KINDS,
    SNAPSHOT_FIELDS, Body, Boundaries, Contact, Geostatic, Grid, Kinematics, Numerics, Polygon, Probe, Rectangle,
)

__all__ = [
    "BOUNDARY_KINDS", "DEFAULT_PRESET", "GEOMETRIES", "KINEMATICS", "NAME", "NUMERICS_CHOICES", "PRESETS",
    "PROBE_KINDS", "SNAPSHOT_FIELDS", "Body", "Boundaries", "Contact", "Geostatic", "Grid", "Kinematics",
    "Numerics", "Polygon", "Probe", "Rectangle", "Scene", "load_scene", "read_material",
    "scene_from_dict", "scene_to_dict",
]
