"""The axisymmetric checks of tests/test_axisymmetric.py at two cell sizes: their errors.

    python benchmarks/axisymmetric_study.py          # prints a markdown table (a few minutes)

Each check is a closed form (docs/validation.md §2, §10, §11); its error measures are
computed by the same functions the tests assert on (imported from the test module, so the
study and the tests cannot drift apart), here at the tests' cell and at half of it. A study,
not a test: it asserts nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CHECKS = [  # (title, error function, cells)
    ("free-standing cylinder under self-weight", "free_cylinder_errors", (0.01, 0.005)),
    ("confined column (linear)", "confined_column_errors", (0.01, 0.005)),
    ("expanding cavity (Lamé)", "cavity_errors", (0.01, 0.005)),
    ("prescribed velocity on a confined rod", "rod_wave_errors", (0.01, 0.005)),
]


def main():
    import jax

    jax.config.update("jax_enable_x64", True)
    import tests.test_axisymmetric as checks

    print("| check | error measure (see the function's docstring) | cell h | h/2 |")
    print("|---|---|---:|---:|")
    for title, name, cells in CHECKS:
        function = getattr(checks, name)
        results = [function(cell) for cell in cells]
        for measure in results[0]:
            values = " | ".join(f"{result[measure]:.2e}" for result in results)
            print(f"| {title} (h = {cells[0]:g} m) | {measure} | {values} |", flush=True)


if __name__ == "__main__":
    main()
