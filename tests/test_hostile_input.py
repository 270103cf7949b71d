"""Hostile input: generated malformed and adversarial scene files and overrides.

Whatever the file holds, `jaxmpm check` (every check a run makes before compiling: reading,
the schema, the relations between keys, seeding, overlaps, the memory estimate) exits 0, or
2 with one line that names the key it refused, never a traceback, never a hang in an
allocation the machine cannot hold. Example counts are bounded to keep CI fast; each example
costs milliseconds (nothing is compiled).
"""

import math
import tomllib
import tracemalloc

import tomli_w
from hypothesis import HealthCheck, given, settings, strategies as st

from jaxmpm.cli import main
from tests.scenes import BLOCK

SETTINGS = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture],
                    derandomize=True)
BASE = tomllib.loads(BLOCK + """
[materials.sand]
model = "drucker_prager"
density = 1800.0
young = 1.0e6
poisson = 0.3
friction_angle = 30.0
fluidity = 5.0
exponent = 2.0

[[bodies]]
name = "wall"
material = "sand"
region = { polygon = [[0.0, 0.2], [0.1, 0.2], [0.1, 0.3], [0.0, 0.3]] }
kinematics = { type = "prescribed", time = [0.0, 0.01], velocity = [[0.1, 0.0], [0.0, 0.0]] }

[[contacts]]
pair = ["block", "wall"]
friction = 0.3

[[probes]]
name = "push"
kind = "reaction"
body = "wall"
""")
PEAK_BYTES = 200e6          # no example may allocate more than this (tracemalloc counts numpy's)


def leaf_paths(data, prefix=()):
    """Every (path, value) of the nested dict/list, tables and lists included."""
    found = []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else []
    for key, value in items:
        path = (*prefix, key)
        found.append((path, value))
        found += leaf_paths(value, path)
    return found


PATHS = [path for path, _ in leaf_paths(BASE)]
TABLE_PATHS = [()] + [path for path, value in leaf_paths(BASE) if isinstance(value, dict)]


def key_text(path):
    """How an error names a path: tables dotted, arrays indexed (bodies[1].region.polygon)."""
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
    return text


def apply(data, path, value=None, delete=False):
    """A deep copy of data with the value at path replaced (or deleted)."""
    data = tomllib.loads(tomli_w.dumps(data))
    table = data
    for part in path[:-1]:
        table = table[part]
    if delete:
        del table[path[-1]]
    else:
        table[path[-1]] = value
    return data


HOSTILE_NUMBERS = st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0, -0.0, 1e300, -1e300, 1e-300,
                                   5e-324, 2**63, -(2**63), 10**30, 3])
HOSTILE_VALUES = st.one_of(
    HOSTILE_NUMBERS,
    st.text(max_size=12),
    st.booleans(),
    st.lists(HOSTILE_NUMBERS, max_size=4),
    st.lists(st.lists(HOSTILE_NUMBERS, max_size=3), max_size=4),
    st.dictionaries(st.text(min_size=1, max_size=6), HOSTILE_NUMBERS, max_size=2),
)


def check(tmp_path, data: bytes, *sets):
    """(exit status, stderr) of `jaxmpm check` on a scene file holding `data`, and the peak of
    numpy/Python allocations it made."""
    path = tmp_path / "scene.toml"
    path.write_bytes(data)
    arguments = ["check", str(path), "--quick"]
    for assignment in sets:
        arguments += ["--set", assignment]
    tracemalloc.start()
    try:
        status = main(arguments)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return status, peak


def assert_one_clear_line(status, capsys, peak, *names):
    captured = capsys.readouterr()
    assert peak < PEAK_BYTES, f"allocated {peak / 1e6:.0f} MB"
    if status == 0:
        assert "ok" in captured.out
        return
    assert status == 2
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    assert lines[0].startswith("jaxmpm: error: ")
    if names:
        assert any(name in lines[0] for name in names), (names, lines[0])


def test_the_base_scene_is_valid(tmp_path, capsys):
    status, peak = check(tmp_path, tomli_w.dumps(BASE).encode())
    assert status == 0, capsys.readouterr().err
    assert_one_clear_line(status, capsys, peak)


def names_for(path):
    """Key names an error about `path` may use: the path itself, or a key it is checked with
    (an array's entries are named through the array; a region's through the region)."""
    text = key_text(path)
    names = {text, key_text(path[:-1]) if len(path) > 1 else text}
    for length in range(1, len(path)):
        names.add(key_text(path[:length]) + ".")
        names.add(key_text(path[:length]) + " ")
    return tuple(names)


@SETTINGS
@given(path=st.sampled_from(PATHS), value=HOSTILE_VALUES)
def test_a_hostile_value_anywhere_is_refused_in_one_line(tmp_path, capsys, path, value):
    data = apply(BASE, path, value)
    status, peak = check(tmp_path, tomli_w.dumps(data).encode())
    # A value that changes what other keys mean is named with them: the grid's size or cell
    # with every body and probe it no longer holds, a time step with the duration, and so on.
    related = ("grid.", "bodies[", "probes[", "scene.", "numerics.", "materials.", "contacts[", "the scene needs")
    assert_one_clear_line(status, capsys, peak, *names_for(path), *related)


@SETTINGS
@given(path=st.sampled_from(PATHS))
def test_a_missing_key_anywhere_is_refused_or_defaulted(tmp_path, capsys, path):
    status, peak = check(tmp_path, tomli_w.dumps(apply(BASE, path, delete=True)).encode())
    assert_one_clear_line(status, capsys, peak)


@SETTINGS
@given(table=st.sampled_from(TABLE_PATHS), name=st.text(min_size=1, max_size=10), value=HOSTILE_VALUES)
def test_an_unknown_key_anywhere_is_named(tmp_path, capsys, table, name, value):
    existing = BASE
    for part in table:
        existing = existing[part]
    if name in existing:
        return
    data = apply(BASE, (*table, name), value)
    status, peak = check(tmp_path, tomli_w.dumps(data).encode())
    if table and table[-1] == "materials":      # a new [materials.NAME] table: a material, not a key
        assert_one_clear_line(status, capsys, peak, key_text((*table, name)))
        return
    assert status == 2
    assert_one_clear_line(status, capsys, peak, name if name.isprintable() else "")


@SETTINGS
@given(raw=st.binary(max_size=200))
def test_bytes_that_are_not_a_scene_are_refused_in_one_line(tmp_path, capsys, raw):
    status, peak = check(tmp_path, raw)
    assert status == 2
    assert_one_clear_line(status, capsys, peak, "not UTF-8", "not valid TOML", "is missing", "must be")


@SETTINGS
@given(cut=st.integers(min_value=0, max_value=len(tomli_w.dumps(BASE))))
def test_a_truncated_scene_file_is_refused_in_one_line(tmp_path, capsys, cut):
    status, peak = check(tmp_path, tomli_w.dumps(BASE).encode()[:cut])
    assert_one_clear_line(status, capsys, peak)


KEYS = ["grid.cell", "grid.size", "scene.duration", "scene.dt", "numerics.ppc", "soil.young", "sand.fluidity",
        "materials.sand.friction_angle", "contacts.block/wall.friction", "bodies.wall.velocity",
        "bodies.block.velocity", "probes.push.body", "nowhere.key", "grid", "soil", "scene.duration.x", "", "=",
        "bodies.ghost.velocity", "contacts.block/ghost.friction"]


@SETTINGS
@given(key=st.one_of(st.sampled_from(KEYS), st.text(max_size=20)),
       value=st.one_of(st.sampled_from(["nan", "inf", "-1", "0", "1e300", "[1, 2, 3]", "[[0, 0]]", '"x"', "{}",
                                        "[", "true", "1e-300"]), st.text(max_size=10)))
def test_a_hostile_override_is_refused_in_one_line(tmp_path, capsys, key, value):
    status, peak = check(tmp_path, tomli_w.dumps(BASE).encode(), f"{key}={value}")
    assert_one_clear_line(status, capsys, peak)


DEGENERATE = st.sampled_from([
    [[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]],                         # collinear: no area
    [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]],                         # one point thrice
    [[0.0, 0.0], [0.2, 0.2], [0.2, 0.0], [0.0, 0.2]],             # self-intersecting bow tie
    [[0.0, 0.0], [1e-9, 0.0], [0.0, 1e-9]],                       # smaller than a sub-cell
    [[-1.0, 0.0], [0.1, 0.0], [0.1, 0.1]],                        # outside the grid
    [[0.0, 0.0], [0.4, 0.0], [0.4, 0.2], [0.0, 0.2]],             # on top of the block
    [[0.0, 0.0], [0.1, 0.1]],                                     # two vertices
])


@SETTINGS
@given(vertices=DEGENERATE, body=st.sampled_from([0, 1]))
def test_degenerate_overlapping_and_empty_bodies_are_refused_in_one_line(tmp_path, capsys, vertices, body):
    data = apply(BASE, ("bodies", body, "region"), {"polygon": vertices})
    status, peak = check(tmp_path, tomli_w.dumps(data).encode())
    assert_one_clear_line(status, capsys, peak, f"bodies[{body}]", f"bodies[{1 - body}]")


@SETTINGS
@given(cell=st.sampled_from([1e-4, 1e-5, 1e-7]), size=st.sampled_from([[0.4, 0.3], [400.0, 300.0], [4e6, 3e6]]))
def test_a_grid_too_large_for_memory_is_refused_with_the_estimate(tmp_path, capsys, cell, size):
    data = apply(apply(BASE, ("grid", "cell"), cell), ("grid", "size"), size)
    data = apply(data, ("bodies", 0, "region"), {"rectangle": [[0.0, 0.0], [size[0], size[1] / 2]]})
    status, peak = check(tmp_path, tomli_w.dumps(data).encode())
    assert status == 2
    assert_one_clear_line(status, capsys, peak, "the scene needs about")


def test_a_file_of_the_other_kind_is_named_as_such(capsys):
    # A calibration file given to `run`, and a scene file given to `calibrate`: one sentence
    # saying which kind of file it is and which command takes it (not "grid is not a known key").
    from pathlib import Path

    examples = Path(__file__).parents[1] / "examples"
    assert main(["run", str(examples / "calibrate_twin.calibration.toml")]) == 2
    assert "is a calibration file" in capsys.readouterr().err
    assert main(["calibrate", str(examples / "calibrate_twin_scene.toml")]) == 2
    assert "is a scene file" in capsys.readouterr().err
