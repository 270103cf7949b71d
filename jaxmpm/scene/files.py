"""Reading and writing scene files: TOML text <-> nested dicts <-> a `Scene`'s parts.

Reading is `jaxmpm.keys.read_section` over `SCENE_FILE` (types, choices, ranges, unknown and
missing keys), then the parts are built (`scene_arguments`); `Scene.from_dict` builds the
scene from them, which runs the checks that relate keys (`jaxmpm.scene.checks`). Writing
states what the scene holds, leaving out the numerics its preset filled in, so that
`Scene.from_toml(scene.to_toml()) == scene`. This module knows the parts, not `Scene`.
"""

from __future__ import annotations

import tomllib

import tomli_w

from jaxmpm.errors import SceneError
from jaxmpm.keys import read_section
from jaxmpm.materials import MODELS
from jaxmpm.scene.parameters import qualify
from jaxmpm.scene.parts import Body, Boundaries, Contact, Geostatic, Grid, Kinematics, Numerics, Polygon, Probe, Rectangle
from jaxmpm.scene.schema import MATERIAL, SCENE_FILE


# --------------------------------------------------------------------------- reading


def read_scene_file(path) -> dict:
    """The nested dict of a TOML scene file (SceneError if it cannot be read, is not TOML, or is
    a calibration file)."""
    try:
        with open(path, "rb") as stream:
            data = stream.read()
    except OSError as error:
        raise SceneError(f"cannot read scene file {str(path)!r}: {error.strerror}.") from None
    try:
        text = data.decode()
    except UnicodeDecodeError as error:
        raise SceneError(f"scene file {str(path)!r} is not UTF-8 text (byte {error.start}).") from None
    data = toml_values(text)
    calibration_keys = [key for key in ("fit", "observations", "experiments", "optimizer") if key in data]
    if calibration_keys and "grid" not in data:
        raise SceneError(f"{str(path)!r} is a calibration file (it has `{calibration_keys[0]}`), not a scene file: "
                         f"give it to `jaxmpm calibrate`, or give a scene file here.")
    return data


def toml_values(text: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"the scene is not valid TOML: {error}.") from None


def scene_arguments(data) -> dict:
    """The keyword arguments of a `Scene` (its parts built) from the nested dict of a TOML file."""
    values = read_section(SCENE_FILE, data, "")
    grid = values["grid"]
    return dict(
        grid=Grid(size=grid["size"], cell=grid["cell"], origin=grid["origin"], boundaries=Boundaries(**grid["boundaries"])),
        materials={name: _material(entry) for name, entry in values["materials"].items()},
        bodies=tuple(_body(entry) for entry in values["bodies"]),
        numerics=Numerics(**values["numerics"]),
        probes=tuple(Probe(**entry) for entry in values["probes"]),
        contacts=tuple(Contact(**entry) for entry in values["contacts"]),
        **values["scene"],
    )


def read_material(data, path="material"):
    """A material object from a [materials.NAME] table (values may be JAX values)."""
    return _material(read_section(MATERIAL, data, path))


def _material(values: dict):
    values = dict(values)
    return MODELS[values.pop("model")](**values)


def _body(values: dict) -> Body:
    region = values["region"]
    region = Rectangle(*region["rectangle"]) if "rectangle" in region else Polygon(region["polygon"])
    stress = values["initial_stress"]
    return Body(
        name=values["name"],
        material=values["material"],
        region=region,
        velocity=values["velocity"],
        kinematics=Kinematics(**values["kinematics"]),
        initial_stress=None if stress is None else Geostatic(**stress["geostatic"]),
    )


# --------------------------------------------------------------------------- writing


def _toml(value):
    """A value as TOML holds it: tuples as lists, None left out by the caller."""
    if isinstance(value, tuple):
        return [_toml(item) for item in value]
    return value


def _given(pairs) -> dict:
    return {name: _toml(value) for name, value in pairs if value is not None}


def scene_to_dict(scene) -> dict:
    """The nested dict of a Scene, which `Scene.from_dict` reads back into an equal one."""
    names = [key.name for key in SCENE_FILE.key("scene").section.keys]
    grid = scene.grid
    data = {
        "scene": _given((name, getattr(scene, name)) for name in names),
        "grid": {"origin": list(grid.origin), "size": list(grid.size), "cell": grid.cell,
                 "boundaries": _given(vars(grid.boundaries).items())},
        "numerics": scene.numerics.given(),
        "materials": {name: {"model": material.model} | _given(vars(material).items())
                      for name, material in scene.materials.items()},
        "bodies": [_body_to_dict(body) for body in scene.bodies],
    }
    if scene.probes:
        data["probes"] = [_given(vars(probe).items()) for probe in scene.probes]
    if scene.contacts:
        data["contacts"] = [_given(vars(contact).items()) for contact in scene.contacts]
    return data


def _body_to_dict(body: Body) -> dict:
    if isinstance(body.region, Rectangle):
        region = {"rectangle": [list(body.region.lower), list(body.region.upper)]}
    else:
        region = {"polygon": _toml(body.region.vertices)}
    entry = {"name": body.name, "material": body.material, "region": region,
             "kinematics": _given(vars(body.kinematics).items())}
    if body.kinematics.type != "prescribed":
        entry["velocity"] = list(body.velocity)
    if body.initial_stress is not None:
        entry["initial_stress"] = {"geostatic": {"k0": body.initial_stress.k0}}
    return entry


def toml_text(data: dict) -> str:
    return tomli_w.dumps(data)


# --------------------------------------------------------------------------- one value


def _names_a_key(scene, full: str) -> bool:
    """Whether "materials.NAME.KEY", "bodies.NAME.KEY" or "contacts.PAIR.KEY" names a key the
    scene file has for that material, body or contact pair."""
    namespace, owner, *rest = full.split(".")
    if len(rest) != 1:
        return False
    if namespace == "materials":
        material = scene.materials.get(owner)
        return material is not None and rest[0] in {key.name for key in material.keys}
    if namespace not in ("bodies", "contacts"):
        return False
    return rest[0] in SCENE_FILE.key(namespace).section.all_names()


def dict_with_value(scene, key: str, value) -> dict:
    """`Scene.with_value`: the scene's nested dict with the value at dotted `key` replaced (see
    there)."""
    data = scene_to_dict(scene)
    owners = {"materials": tuple(scene.materials), "contacts": tuple(c.name for c in scene.contacts),
              "bodies": tuple(body.name for body in scene.bodies)}
    head = key.partition(".")[0]
    if head not in data and head not in ("scene", "grid", "numerics", "probes"):
        try:
            key = qualify(key, owners, lambda full: _names_a_key(scene, full))
        except SceneError as error:
            raise SceneError(f"--set {key}: {error}") from None
    parts = key.split(".")
    if parts[0] == "contacts" and len(parts) == 3:
        if parts[1] not in owners["contacts"]:
            raise SceneError(f"--set {key}: there is no contact pair {parts[1]!r} (pairs: {', '.join(owners['contacts']) or 'none'}).")
        parts[1] = owners["contacts"].index(parts[1])
    elif parts[0] in ("bodies", "probes") and len(parts) > 2:
        names = [entry["name"] for entry in data[parts[0]]]
        if parts[1] not in names:
            raise SceneError(f"--set {key}: there is no {parts[0][:-1]} named {parts[1]!r}.")
        parts[1] = names.index(parts[1])
        entry = data[parts[0]][parts[1]]
        if parts[0] == "bodies" and parts[2:] == ["velocity"] and entry["kinematics"]["type"] == "prescribed":
            parts[2:] = ["kinematics", "velocity"]
    table = data
    for part in parts[:-1]:
        if isinstance(part, int):
            table = table[part]
            continue
        if not isinstance(table, dict) or not isinstance(table.get(part), (dict, list)):
            raise SceneError(f"--set {key}: the scene has no section {part!r} there.")
        table = table[part]
    if not isinstance(table, dict):
        raise SceneError(f"--set {key}: {parts[-1]!r} is not a key of a table.")
    table[parts[-1]] = value
    return data
