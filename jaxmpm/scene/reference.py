"""docs/scene_reference.md, generated from the schemas: `python -m jaxmpm.scene.reference`.

The scene file's keys (`jaxmpm.scene.schema.SCENE_FILE`, the materials' own keys); the
calibration file has its own page (`inverse.reference`). tests/test_scene.py regenerates the
page and compares, so it cannot fall behind the code.
"""

import sys
from pathlib import Path

from jaxmpm.keys import reference_tables
from jaxmpm.scene.schema import SCENE_FILE

PAGE = Path(__file__).resolve().parents[2] / "docs" / "scene_reference.md"

INTRO = """\
# Scene file reference

Generated from the schemas in the code (`python -m jaxmpm.scene.reference`; a test checks
that this page is current). Units are SI, angles in degrees. A key given where it does not
belong, misspelled or of the wrong kind is refused with one sentence naming it (and the
closest known key), before anything is compiled. The checks that relate keys — a body inside
the grid and on a defined material, unique names, contact pairs and probe targets that exist,
an explicit `dt` below the stable limit, the axisymmetric restrictions — are listed at the end.

Kinds: `[x, y]` a pair of numbers, `[[x, y], ...]` a list of pairs; in the allowed column
`(a, b]` is an interval (a excluded, b included). "—" means absent: the meaning says what
happens then. The calibration file's keys are in
[calibration_reference.md](calibration_reference.md).

# The scene file (`jaxmpm run SCENE.toml`)
"""

CHECKS = """\
## Checks that relate keys

- `grid.size` is a whole number of cells of `grid.cell`; every vertex of every body's region
  and every displacement probe's `at` lies inside the grid.
- `bodies[i].material` names a `[materials.NAME]` table; material, body and probe names are
  letters, digits, `_` and `-`, start with a letter or `_`, are not `time`; body names and
  probe names are unique.
- A rectangle goes from its lower-left to its upper-right corner; a polygon has at least 3
  vertices. Bodies may not overlap (checked when the `Simulation` is built, on the seeded points).
- A prescribed body's velocity is `kinematics.velocity` (not `velocity`); with `time` it is a
  table of the same length, `time` starts at 0 and increases strictly. Only free bodies take
  `initial_stress`; `k0 = "jaky"` needs a material with a friction angle.
- Drucker–Prager: `dilation_angle` ≤ `friction_angle`; `exponent` only with `fluidity`.
- A contact pair names two different bodies, at least one free, each pair once; a
  `contact_force` probe names a declared pair, and its `facing`, if given, is not [0, 0]; a
  `reaction` probe a prescribed body.
- `scene.output_every` ≤ `scene.duration`; an explicit `scene.dt` is at most the stable limit
  h / max(c_p + |v|).
- Axisymmetry: `grid.origin[0] = 0` (the axis), `grid.boundaries.left` is `slip` or `fixed`,
  `gravity[0] = 0`, no rigid bodies.
- `numerics.dtype = "float64"` needs JAX's 64-bit mode (checked when the `Simulation` is built).
"""


def markdown() -> str:
    lines = [INTRO] + reference_tables(SCENE_FILE, "", "")[2:] + [CHECKS]
    return "\n".join(lines).rstrip() + "\n"


def write_page(default, text, argv=None):
    """Write `text` to the path in argv (or `default`) and say so."""
    target = Path((argv or sys.argv[1:] or [default])[0])
    target.write_text(text)
    print(f"wrote {target}")


def main(argv=None):
    write_page(PAGE, markdown(), argv)


if __name__ == "__main__":
    main()
