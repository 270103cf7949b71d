"""Small scenes shared by the tests, as TOML text (the format users write)."""

BLOCK = """
[scene]
name = "block"
gravity = [0.0, -9.81]
duration = 0.01
output_every = 0.005

[grid]
size = [0.4, 0.3]
cell = 0.05
boundaries = { left = "slip", right = "slip", bottom = "fixed", top = "free" }

[numerics]
shape = "linear"
transfer = "flip"
ppc = 2
damping = 0.0

[materials.soil]
model = "linear_elastic"
density = 1800.0
young = 1.0e6
poisson = 0.3

[[bodies]]
name = "block"
material = "soil"
region = { rectangle = [[0.0, 0.0], [0.4, 0.2]] }

[[probes]]
name = "top"
kind = "displacement"
at = [0.2, 0.2]

[[probes]]
name = "block_move"
kind = "body_displacement"
body = "block"
"""
