"""docs/calibration_reference.md, generated from the calibration file's schema
(`inverse.config.CALIBRATION_FILE`): `python -m inverse.reference`. tests/test_scene.py
regenerates the page and compares, so it cannot fall behind the code.
"""

from pathlib import Path

from inverse.config import CALIBRATION_FILE
from jaxmpm.keys import reference_tables
from jaxmpm.scene.reference import write_page

PAGE = Path(__file__).resolve().parents[1] / "docs" / "calibration_reference.md"

INTRO = """\
# Calibration file reference

Generated from the schema in the code (`python -m inverse.reference`; a test checks that this
page is current). The conventions (kinds, units, intervals, "—") are those of
[scene_reference.md](scene_reference.md), which lists the scene file's keys.

# The calibration file (`jaxmpm calibrate CONFIG.toml -o FIT.h5`)
"""


def markdown() -> str:
    lines = [INTRO] + reference_tables(CALIBRATION_FILE, "CONFIG.toml", "")[2:]
    return "\n".join(lines).rstrip() + "\n"


def main(argv=None):
    write_page(PAGE, markdown(), argv)


if __name__ == "__main__":
    main()
