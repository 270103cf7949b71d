"""Scenes: the TOML scene format, read into frozen dataclasses and checked before compiling.

- `model`: the dataclasses (`Scene`, `Grid`, `Body`, ...), the presets, derived facts;
- `schema`: every key of the file once (kind, unit, default, range, meaning);
- `files`: TOML <-> dicts <-> `Scene`, read through the schema; `with_value`;
- `checks`: the schema's checks on any `Scene`, and those that relate keys;
- `reference`: docs/scene_reference.md, generated from the schema.
"""

from jaxmpm.scene.files import load_scene, read_material, scene_from_dict, scene_to_dict
from jaxmpm.scene.model import (
    BOUNDARY_KINDS, DEFAULT_PRESET, GEOMETRIES, KINEMATICS, NAME, NUMERICS_CHOICES, PRESETS, PROBE_KINDS,
    SNAPSHOT_FIELDS, Body, Boundaries, Contact, Geostatic, Grid, Kinematics, Numerics, Polygon, Probe, Rectangle,
    Scene,
)

__all__ = [
    "BOUNDARY_KINDS", "DEFAULT_PRESET", "GEOMETRIES", "KINEMATICS", "NAME", "NUMERICS_CHOICES", "PRESETS",
    "PROBE_KINDS", "SNAPSHOT_FIELDS", "Body", "Boundaries", "Contact", "Geostatic", "Grid", "Kinematics",
    "Numerics", "Polygon", "Probe", "Rectangle", "Scene", "load_scene", "read_material",
    "scene_from_dict", "scene_to_dict",
]
