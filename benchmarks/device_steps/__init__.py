"""The parts of benchmarks/device_check.py: one module per step, and what the steps share.

  common       paths, JSON files, the context the steps share, a command run in its time box
  settings     the sizes of the steps: the GPU's (FULL) and --smoke's (SMOKE)
  pack         --pack: the data and wheels the device machine lacks, sized against what it carries
  environment  the environment step (devices, XLA flags, packages) and the run's provenance
  correctness  pytest, the files that failed on a GPU before first
  determinism  the same seed's explore twice, byte for byte; WALDO_DETERMINISTIC=0's time
  training     the fox trained into the run folder the later steps read
  rendering    render_trained.py on that run; render_population.py per size
  search       `waldo explore` on that run per resolution
  gradient     gradient_cost.py
  splats       render_splats.py at the GPU targets' sizes; the donut explored
  targets      the issue's targets as target / measured / met

A step module has `step(ctx, deadline) -> {"status", "commands", "result", ...}`; a step whose work
imports JAX runs it in a child process (`device_check.py _environment | _pytest | _train`), whose entry
is the module's `child(argv)`. Standard library only at import: the driver's process never imports JAX.
"""
