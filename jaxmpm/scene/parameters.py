"""The parameter pytree of a scene, and the dotted names that address its values.

    {"materials": {"sand": {"friction_angle": 30.0, "young": 2e7, ...}, ...},
     "contacts":  {"backfill/wall": {"friction": 0.3}},
     "bodies":    {"pile": {"velocity": [0.0, -0.5]}},
     "scene":     {"gravity": [0.0, -9.81]},
     "numerics":  {"damping": 0.1}}

Only the namespaces a scene uses appear: "contacts" with `[[contacts]]` pairs (keyed
"first/second"), "bodies" with prescribed bodies (their velocity: a constant (2,) or one row
per time of the body's table, (K, 2)), "numerics" with local damping (a scene without damping
compiles no damping, so its coefficient is a parameter only where it is non-zero). Every value
is dynamic: `jax.grad`, `jax.vmap` and optax act on it without recompiling (a centrifuge
test's g-level, a damping, fitted or varied over experiments).

Dotted names address the values in `--set`, calibration and `Fit`: in full
("materials.sand.friction_angle", "contacts.backfill/wall.friction", "bodies.pile.velocity",
"scene.gravity", "numerics.damping"), or without the namespace ("sand.friction_angle",
"backfill/wall.friction") where only one namespace has an entry of that name. A trailing
"[i]" names one component of a vector ("scene.gravity[1]", "bodies.pile.velocity[1]").
"""

from __future__ import annotations

import difflib

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.materials import material_parameters

OWNED_NAMESPACES = ("materials", "contacts", "bodies")    # namespace.owner.key
SCENE_NAMESPACES = ("scene", "numerics")                  # namespace.key
NAMESPACES = OWNED_NAMESPACES + SCENE_NAMESPACES
OWNER_KINDS = {"materials": "material", "contacts": "contact pair", "bodies": "body"}


def pair_name(pair) -> str:
    """'first/second': the key of a contact pair in params["contacts"]."""
    return "/".join(pair)


def scene_parameters(scene) -> dict:
    """The parameter pytree of a scene, from its own values."""
    params = {"materials": {name: material_parameters(material) for name, material in scene.materials.items()}}
    if scene.contacts:
        params["contacts"] = {pair_name(contact.pair): {"friction": contact.friction} for contact in scene.contacts}
    prescribed = {body.name: {"velocity": np.asarray(body.kinematics.velocity, float)} for body in scene.bodies
                  if body.kinematics.type == "prescribed"}
    if prescribed:
        params["bodies"] = prescribed
    params["scene"] = {"gravity": np.asarray(scene.gravity, float)}
    if scene.numerics.damping:
        params["numerics"] = {"damping": scene.numerics.damping}
    return params


def qualify(name: str, owners: dict, exists=None) -> str:
    """The full dotted name "namespace.owner.key" of `name`, given the owners of each namespace
    ({namespace: names}). A name that starts with a namespace is kept; otherwise its first part
    must be the owner in exactly one namespace, or, where several namespaces have an owner of
    that name (a body and its material may share one), in exactly one where the full name
    exists (`exists(full name) -> bool`). SceneError (naming `name`) if it is not."""
    head, _, rest = name.partition(".")
    if head in NAMESPACES:
        return name
    holders = [namespace for namespace in OWNED_NAMESPACES if head in owners.get(namespace, ())]
    if len(holders) > 1 and exists is not None:
        named = [namespace for namespace in holders if exists(f"{namespace}.{name}")]
        if not named:
            owners_named = " or ".join(f"{OWNER_KINDS[namespace]} {head!r}" for namespace in holders)
            raise SceneError(f"{name!r}: {rest!r} is not a key of the {owners_named}.")
        holders = named
    if len(holders) == 1:
        return f"{holders[0]}.{name}"
    if len(holders) > 1:
        options = " or ".join(f"'{namespace}.{name}'" for namespace in holders)
        raise SceneError(f"{name!r} is ambiguous: write {options}.")
    known = [owner for namespace in OWNED_NAMESPACES for owner in owners.get(namespace, ())]
    hint = difflib.get_close_matches(head, known, n=1)
    suggestion = f" (did you mean {hint[0]!r}?)" if hint else f" (known: {', '.join(known)})"
    raise SceneError(f"{name!r} names {head!r}, which is not a material, contact pair or body of the scene{suggestion}.")


def flat_parameters(params: dict) -> dict:
    """{"materials.sand.friction_angle": value, "scene.gravity": value, ...}: every value of a
    parameter pytree."""
    flat = {}
    for namespace, entries in params.items():
        for name, entry in entries.items():
            if namespace in SCENE_NAMESPACES:
                flat[f"{namespace}.{name}"] = entry
                continue
            for key, value in entry.items():
                flat[f"{namespace}.{name}.{key}"] = value
    return flat


def split_component(name: str) -> tuple[str, int | None]:
    """("scene.gravity", 1) from "scene.gravity[1]"; (name, None) without a component."""
    if not name.endswith("]") or "[" not in name:
        return name, None
    base, _, index = name[:-1].rpartition("[")
    if not index.strip().isdigit():
        raise SceneError(f"{name!r}: the component in brackets must be a whole number, e.g. 'scene.gravity[1]'.")
    return base, int(index)


def resolve(params: dict, name: str) -> tuple:
    """The location of a dotted name in `params`: (namespace, owner, key) or (namespace, key),
    with the component index appended for "name[i]" (`value_at`); SceneError if it names
    nothing."""
    base, component = split_component(name)
    flat = flat_parameters(params)
    owned = {namespace: tuple(owners) for namespace, owners in params.items() if namespace in OWNED_NAMESPACES}
    full = qualify(base, owned, flat.__contains__)
    if full not in flat:
        hint = difflib.get_close_matches(full, list(flat), n=1)
        suggestion = f" (did you mean {hint[0]!r}?)" if hint else f" (known: {', '.join(flat)})"
        raise SceneError(f"{name!r} is not a parameter of the scene{suggestion}.")
    namespace, rest = full.split(".", 1)
    location = (namespace, rest) if namespace in SCENE_NAMESPACES else (namespace, *rest.rsplit(".", 1))
    if component is None:
        return location
    size = np.size(flat[full])
    if np.ndim(flat[full]) != 1 or component >= size:
        raise SceneError(f"{name!r}: {full!r} has no component {component} (its shape is {np.shape(flat[full])}).")
    return (*location, component)


def location_name(location: tuple) -> str:
    """The full dotted name of a location from `resolve` ("scene.gravity[1]")."""
    names = [part for part in location if not isinstance(part, int)]
    index = f"[{location[-1]}]" if isinstance(location[-1], int) else ""
    return ".".join(names) + index


def value_at(params: dict, location: tuple):
    """The value at a location from `resolve` (a component where it ends with an index)."""
    value = params
    for part in location:
        value = value[part]
    return value


def with_values(params: dict, values: dict) -> dict:
    """A copy of `params` with {dotted name: value} replaced, e.g.
    with_values(sim.params, {"sand.friction_angle": phi}) or {"scene.gravity[1]": -50.0}
    (differentiable: the values may be traced). A value replacing an array takes that array's
    dtype, so a jitted function of the parameters is not traced again for it. SceneError if a
    name is not a parameter."""
    result = jax.tree_util.tree_map(lambda leaf: leaf, params)      # fresh containers
    for name, value in values.items():
        location = resolve(params, name)
        if isinstance(value, (list, tuple)):      # a vector written as a list, as in a scene file
            value = jnp.asarray(value)
        *tables, last = [part for part in location if not isinstance(part, int)]
        if isinstance(location[-1], int):        # one component of a vector
            value = jnp.asarray(value_at(result, location[:-1])).at[location[-1]].set(value)
        replaced = value_at(params, tuple(tables) + (last,))
        if hasattr(replaced, "dtype"):
            value = jnp.asarray(value, replaced.dtype)
        container = result
        for part in tables:
            container[part] = dict(container[part])
            container = container[part]
        container[last] = value
    return result
