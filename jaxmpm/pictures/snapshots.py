"""A run's snapshots read back as per-point fields, for plots and export (host-side numpy).

Points of all bodies are joined in scene order (the order of `[[bodies]]`), each tagged with
its body number. Besides the stored fields (`x`, `v`, `displacement`, `stress`,
`plastic_strain`, `volume`, `mass`), scalars derived from them can be asked for by name:

    p             mean pressure -tr(sigma)/3, compression positive [Pa]
    q             von Mises stress sqrt(3/2 s:s) [Pa]
    sigma_xx, sigma_yy, sigma_xy, sigma_zz   stress components [Pa] (tension positive), in
                  plane strain (sigma_zz is the out-of-plane stress)
    sigma_rr, sigma_zz, sigma_rz, sigma_tt   the same in axisymmetry, where x is the radius r
                  and y the axial z: sigma_zz is the axial stress, sigma_tt the hoop stress
    displacement  |u| [m] (from the stored displacement, or x minus its first snapshot)
    speed         |v| [m/s]

The stress components of each geometry are the names valid for its files; asking for the
other geometry's names is an error (sigma_zz, valid in both, is a different component).
In axisymmetry `mass` and `volume` are per radian (the ring a point stands for has 2 pi times).
"""

from __future__ import annotations

import functools

import numpy as np

from jaxmpm.errors import SceneError
from jaxmpm.scene import Scene

# Stress components by name, for each geometry: tensors are ordered (x, y, z) in plane strain
# and (r, z, theta) in axisymmetry.
STRESS_NAMES = {
    "plane_strain": {"sigma_xx": (0, 0), "sigma_yy": (1, 1), "sigma_xy": (0, 1), "sigma_zz": (2, 2)},
    "axisymmetric": {"sigma_rr": (0, 0), "sigma_zz": (1, 1), "sigma_rz": (0, 1), "sigma_tt": (2, 2)},
}
GEOMETRY_WORDS = {"plane_strain": "plane-strain", "axisymmetric": "axisymmetric"}


def derived_fields(geometry):
    """{scalar name: the stored field it is computed from} for files of `geometry`."""
    return {"p": "stress", "q": "stress", **{name: "stress" for name in STRESS_NAMES[geometry]}, "speed": "v"}


class Snapshots:
    """The snapshots of a `Result`: `len(snapshots)`, `times`, `positions(k)`, `field(name, k)`."""

    def __init__(self, result):
        self.scene = Scene.from_toml(result.scene_toml)
        self.geometry = self.scene.geometry
        self.axisymmetric = self.geometry == "axisymmetric"
        self.components = STRESS_NAMES[self.geometry]
        self.derived = derived_fields(self.geometry)
        self.times = np.asarray(result.snapshots["time"])
        self.bodies = [body.name for body in self.scene.bodies if body.name in result.snapshots]
        fields = list(result.snapshots[self.bodies[0]]) if self.bodies else []
        self.stored = {field: [np.asarray(result.snapshots[body][field]) for body in self.bodies] for field in fields}
        counts = [per_body.shape[1] for per_body in self.stored[fields[0]]] if fields else []
        self.body_number = np.repeat(np.arange(len(counts)), counts)
        # prescribed and rigid bodies have no stress update: their stress and plastic strain say nothing
        deforms = [self.scene.body_named(name).kinematics.type == "free" for name in self.bodies]
        self.deforming = np.repeat(np.asarray(deforms, bool), counts)

    @functools.cached_property
    def seeded_positions(self):
        """(N, 2) initial point positions, seeded again from the scene (done once)."""
        from jaxmpm.scene.seeding import seed_bodies

        return seed_bodies(self.scene).positions

    def __len__(self):
        return len(self.times)

    def stored_field(self, name, index):
        """A stored field at snapshot `index`, all bodies joined: (N, ...)."""
        return np.concatenate([per_body[index] for per_body in self.stored[name]])

    def positions(self, index):
        """(N, 2) point positions [m] at snapshot `index`: the stored `x`, or the seeded
        positions plus the stored `displacement`."""
        if "x" in self.stored:
            return self.stored_field("x", index)
        if "displacement" in self.stored:
            return self.seeded_positions + self.stored_field("displacement", index)
        raise SceneError(
            "the output file holds neither 'x' nor 'displacement' snapshots, so the points cannot "
            "be placed: add one of them to scene.snapshot_fields."
        )

    def names(self):
        """Every scalar field (one number per point) this file can give: what a plot colours
        by. Vector and tensor fields enter through their scalars (speed, |u|, p, q, ...)."""
        scalars = [name for name in ("plastic_strain", "volume", "mass") if name in self.stored]
        scalars += [name for name, source in self.derived.items() if source in self.stored]
        if "displacement" in self.stored or "x" in self.stored:
            scalars.append("displacement")
        return sorted(set(scalars) | {"body"})

    def field(self, name, index):
        """Scalar field `name` at snapshot `index`, all bodies joined: (N,)."""
        if name not in self.names():
            other = next((geometry for geometry, names in STRESS_NAMES.items()
                          if geometry != self.geometry and name in names), None)
            why = (f"is a {GEOMETRY_WORDS[other]} stress name and this output file is {GEOMETRY_WORDS[self.geometry]}"
                   if other else "cannot colour the points of this output file")
            raise SceneError(f"field {name!r} {why}; choose one of {', '.join(self.names())}.")
        if name == "body":
            return self.body_number
        if name == "displacement":
            moved = (self.stored_field("displacement", index) if "displacement" in self.stored
                     else self.positions(index) - self.positions(0))
            return np.linalg.norm(moved, axis=1)
        if name == "speed":
            return np.linalg.norm(self.stored_field("v", index), axis=1)
        if name in self.components:
            row, column = self.components[name]
            return self.stored_field("stress", index)[:, row, column]
        if name in self.derived:
            return stress_scalar(name, self.stored_field("stress", index))
        return self.stored_field(name, index)


def stress_scalar(name, stress):
    """p (-tr(sigma)/3, compression positive) or q of (N, 3, 3) stresses (tension positive)."""
    pressure = -np.trace(stress, axis1=1, axis2=2) / 3.0
    if name == "p":
        return pressure
    deviator = stress + pressure[:, None, None] * np.eye(3)
    return np.sqrt(1.5 * np.sum(deviator * deviator, axis=(1, 2)))
