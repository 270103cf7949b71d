"""`jaxmpm design DESIGN.toml`: which candidate experiments would identify the parameters
(inverse.design), from a declarative design file; added to `jaxmpm` through the entry point
group `jaxmpm.commands` (pyproject.toml), like `calibrate`.

    jaxmpm design DESIGN.toml [-o DESIGN.h5] [-o DESIGN.csv] [-o DESIGN.png]

The design file (paths relative to it; keys: docs/experiment_design.md):

    scene = "footing.toml"             # the candidates' scene unless one names its own
    k = 2                              # optional: greedy selection of k candidates
    guesses = "corners"                # optional: "guess" (default), "corners", or a count

    [parameters]                       # what to identify: a guess, and optionally a prior range
    "sand.fluidity" = { guess = 5.0, low = 1.0, high = 20.0 }
    "sand.exponent" = 2.0

    [[candidates]]
    name = "slow"
    set = { "bodies.footing.velocity" = [0.0, -0.02] }    # optional: its own parameter values
    scene_values = { "scene.duration" = 0.3 }             # optional: its own scene values
    probes.force = { components = [1], every = 0.01, noise = 5.0 }
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from jaxmpm.errors import SceneError
from jaxmpm.keys import Key, Section, read_section

PROBE = Section((
    Key("times", "floats", "the observation times (or give every)", unit="s", default=None, low=0.0,
        low_inclusive=True),
    Key("every", "float", "observe every this many seconds, from this time to the end of the run (or give times)",
        unit="s", default=None, low=0.0),
    Key("noise", "floats", "the noise standard deviation of the probe, in its units: one number, or one per "
        "observed component", low=0.0),
    Key("components", "floats", "the observed components of the probe (e.g. [1] for a vertical displacement; "
        "absent: all)", default=None, low=0.0, low_inclusive=True),
    Key("window", "float", "each value is the probe's mean over this window, centred on its time", unit="s",
        default=None, low=0.0, low_inclusive=True),
), "one observed probe of a candidate: when it is read, its noise")
CANDIDATE = Section((
    Key("name", "str", "the candidate's name in outputs (absent: candidate_k)", default=None),
    Key("scene", "str", "the scene file, relative to the design file (absent: the top-level scene)", default=None),
    Key("set", "mapping", "this candidate's own parameter values: dotted name = value (e.g. a pile velocity); "
        "candidates of one scene share one compiled simulation", default={}),
    Key("scene_values", "mapping", "this candidate's own scene values: dotted name = value (e.g. "
        "scene.duration, grid.cell), each different set making its own simulation", default={}),
    Key("probes", "named_tables", "the observed probes, by name", section=PROBE),
), "one candidate experiment: a scene, its own values, what is observed")
DESIGN_FILE = Section((
    Key("scene", "str", "the scene file of every candidate that names none, relative to this file", default=None),
    Key("parameters", "mapping", "the parameters to identify: \"dotted.name\" = guess, or { guess, low, high } "
        "(a prior range: its corners or samples test the design's robustness)"),
    Key("candidates", "tables", "the candidate experiments", section=CANDIDATE),
    Key("k", "int", "choose the best k candidates greedily by D-optimality (absent: no selection)", default=None,
        low=1, low_inclusive=True),
    Key("guesses", "str", "where the design is evaluated: 'guess', 'corners' (and every corner of the prior "
        "ranges), or 'samples' (and `samples` draws in them)", default="guess",
        choices=("guess", "corners", "samples")),
    Key("samples", "int", "the number of draws with guesses = 'samples'", default=8, low=1, low_inclusive=True),
    Key("seed", "int", "seed of the draws", default=0),
    Key("threshold", "float", "a direction whose scaled Fisher eigenvalue is below this fraction of the largest "
        "is reported not identified", default=1e-8, low=0.0, high=1.0),
))


@dataclasses.dataclass
class DesignConfig:
    candidates: list        # inverse.Experiment, planned observations
    parameters: dict
    options: dict           # keyword arguments of inverse.design.design


def probe_plan(values: dict, path: str) -> dict:
    """A probe table as `inverse.design.planned_observations` takes it."""
    plan = {key: values[key] for key in ("times", "every", "window") if values[key] is not None}
    components = values["components"]
    if components is not None:
        for index, component in enumerate(components):
            if not float(component).is_integer():
                raise SceneError(f"{path}.components[{index}] = {component!r} must be a whole number.")
        plan["components"] = [int(c) for c in components]
    noise = values["noise"]
    plan["noise"] = noise[0] if len(noise) == 1 else list(noise)
    return plan


def load_design(path) -> DesignConfig:
    """The candidates (one jaxmpm.Simulation per scene file and scene values), parameters and
    options of a design file; every check that needs no compiling."""
    import jaxmpm
    from inverse.config import read_toml
    from inverse.design import planned_observations
    from inverse.experiments import Experiment

    path = Path(path)
    data = read_toml(path, "design file")
    if "grid" in data and "candidates" not in data:
        raise SceneError(f"{str(path)!r} is a scene file (it has [grid]), not a design file: name it as the scene "
                         "of a design file (scene = \"...\").")
    for entry in data.get("candidates", []) if isinstance(data.get("candidates"), list) else []:
        if isinstance(entry, dict):          # a single noise number reads as a list of one
            for plan in (entry.get("probes") or {}).values():
                if isinstance(plan, dict) and isinstance(plan.get("noise"), (int, float)):
                    plan["noise"] = [plan["noise"]]
    values = read_section(DESIGN_FILE, data, "")
    if not values["candidates"]:
        raise SceneError("candidates must be a non-empty array of tables ([[candidates]]).")
    sims, candidates = {}, []
    for index, entry in enumerate(values["candidates"]):
        label = f"candidates[{index}]"
        scene_name = entry["scene"] or values["scene"]
        if scene_name is None:
            raise SceneError(f"{label}.scene is missing: give it, or a top-level scene for every candidate.")
        key = (str((path.parent / scene_name).resolve()), repr(sorted(entry["scene_values"].items())))
        if key not in sims:
            scene = jaxmpm.load_scene(path.parent / scene_name)
            for name, value in entry["scene_values"].items():
                try:
                    scene = scene.with_value(name, value)
                except SceneError as error:
                    raise SceneError(f"{label}.scene_values: {error}") from None
            sims[key] = jaxmpm.Simulation(scene)
        plans = {name: probe_plan(plan, f"{label}.probes.{name}") for name, plan in entry["probes"].items()}
        observations = planned_observations(sims[key], plans, f"{label}.probes")
        candidates.append(Experiment(sims[key], observations, entry["set"], entry["name"] or f"candidate_{index}"))
    guesses = {"guess": "guess", "corners": "corners", "samples": values["samples"] + 1}[values["guesses"]]
    options = dict(k=values["k"], guesses=guesses, seed=values["seed"], threshold=values["threshold"])
    return DesignConfig(candidates, dict(values["parameters"]), options)


OUTPUT_TYPES = (".h5", ".hdf5", ".csv", ".png", ".pdf", ".svg")


class DesignCommand:
    help = "predict how well candidate experiments would identify parameters (Fisher information)"

    @staticmethod
    def add_arguments(parser):
        parser.add_argument("design", help="design file (TOML; keys: docs/experiment_design.md)")
        parser.add_argument("-o", "--output", action="append", default=[],
                            help="an output, by its type: .h5 (default: DESIGN name with .h5), .csv, or a plot "
                                 ".png/.pdf/.svg of the predicted error ellipses; repeat for several")

    @staticmethod
    def run(arguments) -> int:
        import jax

        jax.config.update("jax_enable_x64", True)
        import jaxmpm
        from inverse.design import design
        from jaxmpm.cli import output_path

        outputs = [output_path(name, arguments.design) for name in arguments.output] or [
            output_path(None, arguments.design)]
        for output in outputs:
            if output.suffix.lower() not in OUTPUT_TYPES:
                raise SceneError(f"-o {str(output)!r}: the file type must be one of {', '.join(OUTPUT_TYPES)}.")
        jaxmpm.use_compilation_cache()
        config = load_design(arguments.design)
        try:
            result = design(config.candidates, config.parameters, **config.options)
        except jaxmpm.SimulationError as error:
            print(f"jaxmpm: {error}", file=sys.stderr)
            return 1
        print(result.summary())
        for output in outputs:
            if output.suffix.lower() in (".png", ".pdf", ".svg"):
                import matplotlib

                matplotlib.use("Agg")
                result.plot(output)
            else:
                result.save(output)
            print(f"wrote {output}")
        return 0


DESIGN = DesignCommand()


def reference_markdown() -> str:
    """The design file's keys as markdown tables (docs/experiment_design.md holds them between
    the markers of `REFERENCE_MARKERS`; tests/test_design.py checks they are current)."""
    from jaxmpm.keys import reference_tables

    return "\n".join(reference_tables(DESIGN_FILE, "DESIGN.toml", "", level=3)).rstrip() + "\n"


REFERENCE_MARKERS = ("<!-- design file keys: generated by python -m inverse.design_command -->",
                     "<!-- end of the generated keys -->")


def main():
    """Rewrite the generated keys in docs/experiment_design.md."""
    page = Path(__file__).resolve().parents[1] / "docs" / "experiment_design.md"
    text = page.read_text()
    start, end = (text.index(marker) for marker in REFERENCE_MARKERS)
    page.write_text(text[:start + len(REFERENCE_MARKERS[0])] + "\n\n" + reference_markdown() + "\n" + text[end:])
    print(f"wrote {page}")


if __name__ == "__main__":
    main()
