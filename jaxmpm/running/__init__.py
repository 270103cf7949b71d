"""Running a scene and keeping its output: the host side around the step.

- `simulation`: `Simulation`, the differentiable description (structure, params, initial
  state, step, probes) that users and jaxmpm's inverse module differentiate; `simulate`;
- `parameters`: the parameter pytree and the dotted names that address its values;
- `rollout`: the scan over steps and its checkpointing policies for reverse mode;
- `runner`: a forward run in chunks: progress, streaming, resume, interrupts;
- `output`, `results`: the HDF5 output file, written as the run goes, and read back;
- `budget`, `run_time`: memory and run-time estimates before a run;
- `refinement`: the scene at half the step or cell, and how far a run's probes move there;
- `ensembles`: batches of parameters over devices;
- `compilation_cache`, `tracing`, `progress`: compiled programs kept, traced quickly, shown.
"""
