"""The parameter pytree of a scene, and the dotted names that address its values.

    {"materials": {"sand": {"friction_angle": 30.0, "young": 2e7, ...}, ...},
     "contacts":  {"backfill/wall": {"friction": 0.3}},
     "bodies":    {"pile": {"velocity": [0.0, -0.5]}}}

Only the namespaces a scene uses appear: "contacts" with `[[contacts]]` pairs (keyed
"first/second"), "bodies" with prescribed bodies (their velocity: a constant (2,) or one row
per time of the body's table, (K, 2)). Every value is dynamic: `jax.grad`, `jax.vmap` and
optax act on it without recompiling.

Dotted names address the values in `--set`, calibration and `Fit`: in full
("materials.sand.friction_angle", "contacts.backfill/wall.friction", "bodies.pile.velocity"),
or without the namespace ("sand.friction_angle", "backfill/wall.friction") where only one
namespace has an entry of that name.
"""

from __future__ import annotations

import difflib

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.materials import material_parameters

NAMESPACES = ("materials", "contacts", "bodies")
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
    holders = [namespace for namespace in NAMESPACES if head in owners.get(namespace, ())]
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
    known = [owner for namespace in NAMESPACES for owner in owners.get(namespace, ())]
    hint = difflib.get_close_matches(head, known, n=1)
    suggestion = f" (did you mean {hint[0]!r}?)" if hint else f" (known: {', '.join(known)})"
    raise SceneError(f"{name!r} names {head!r}, which is not a material, contact pair or body of the scene{suggestion}.")


def flat_parameters(params: dict) -> dict:
    """{"materials.sand.friction_angle": value, ...}: every value of a parameter pytree."""
    return {
        f"{namespace}.{owner}.{key}": value
        for namespace, owners in params.items()
        for owner, values in owners.items()
        for key, value in values.items()
    }


def resolve(params: dict, name: str) -> tuple[str, str, str]:
    """(namespace, owner, key) of a dotted name in `params`; SceneError if it names nothing."""
    flat = flat_parameters(params)
    full = qualify(name, {namespace: tuple(owners) for namespace, owners in params.items()}, flat.__contains__)
    if full not in flat:
        hint = difflib.get_close_matches(full, list(flat), n=1)
        suggestion = f" (did you mean {hint[0]!r}?)" if hint else f" (known: {', '.join(flat)})"
        raise SceneError(f"{name!r} is not a parameter of the scene{suggestion}.")
    namespace, rest = full.split(".", 1)
    owner, key = rest.rsplit(".", 1)
    return namespace, owner, key


def with_values(params: dict, values: dict) -> dict:
    """A copy of `params` with {dotted name: value} replaced, e.g.
    with_values(sim.params, {"sand.friction_angle": phi}) (differentiable: the values may be
    traced). SceneError if a name is not a parameter."""
    result = jax.tree_util.tree_map(lambda leaf: leaf, params)      # fresh containers
    for name, value in values.items():
        namespace, owner, key = resolve(params, name)
        result[namespace] = dict(result[namespace])
        if isinstance(value, (list, tuple)):      # a vector written as a list, as in a scene file
            value = jnp.asarray(value)
        result[namespace][owner] = dict(result[namespace][owner], **{key: value})
    return result
