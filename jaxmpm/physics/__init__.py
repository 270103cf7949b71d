"""The step and its parts: what docs/physics.md describes, in plain JAX.

- `solver`: the step, `step(params, state) -> (state, diagnostics)`, phase by phase;
- `grid`, `shapes`: the background grid, its edges, and the shape functions of the transfers;
- `contact`: the multi-field contact between bodies (normals, Coulomb friction);
- `bodies`: kinematic bodies (free, prescribed, rigid) behind one interface;
- `state`, `tensors`: the particle state and its error bits; stress and strain in Voigt form;
- `seeding`, `initial_stress`: filling bodies with points, the geostatic start;
- `probes`: the quantities recorded every step;
- `time_step`: the one CFL policy that sets and checks the step.

The constitutive laws are in jaxmpm.materials; the speed devices in jaxmpm.kernels.
"""
