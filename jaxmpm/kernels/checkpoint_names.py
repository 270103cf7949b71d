"""The names under which the step marks values for a checkpointing policy
(`jax.ad_checkpoint.checkpoint_name`; the policies: jaxmpm.running.rollout.Checkpointing).
They live here, below both the step and the rollout, so that neither imports the other."""

# The name of the node arrays "recompute_grid" keeps (`jax.ad_checkpoint.checkpoint_name`): what
# the step's particle-to-grid transfers produce (`solver.particles_to_grid`, `remap_velocity`).
KEPT_GRID = "grid"
# The name of the points' velocity gradients "recompute_grid" keeps with 3 x 3 stencils
# (`solver.velocity_gradient`): recomputed, XLA formed them twice, once per layout its readers
# asked for, each time from the 9 gathered node velocities of a point.
KEPT_RATE = "rate"
# The name of the roots of implicit equations a material law solves at each point (the Perzyna
# solve: `materials.drucker_prager.perzyna_fraction`). "recompute" and "recompute_grid" keep
# them, so the step they run again solves nothing.
KEPT_SOLVES = "solve"
