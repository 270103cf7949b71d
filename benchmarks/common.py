"""What several benchmark scripts share: the block scene of the throughput benchmark, the
machine's description, and the writer of a script's own section of docs/benchmarks.md."""

from __future__ import annotations

import datetime
import os
import platform
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
STEPS_PER_CALL = 100                   # steps per `sim._advance` call (one output interval)


def block_material(material: str):
    """The block's material in the benchmark scene (see `block_scene`)."""
    from jaxmpm import DruckerPrager, LinearElastic

    if material == "elastic":
        return LinearElastic(density=1000.0, young=1.0e6, poisson=0.3)
    viscous = {"fluidity": 5.0, "exponent": 2.0} if material == "perzyna" else {}
    return DruckerPrager(density=1000.0, young=1.0e6, poisson=0.3, friction_angle=30.0, **viscous)


def block_scene(cells: int, dtype: str, steps: int, material: str = "elastic", shape: str = "linear",
                transfer: str = "flip"):
    """The benchmark scene: `steps` steps in outputs of STEPS_PER_CALL steps. material:
    "elastic", "drucker_prager" (the same block as sand, phi = 30 deg, which slumps) or
    "perzyna" (that sand viscoplastic, gamma = 5 1/s, N = 2);
    transfer: "flip" (FLIP 0.99) or "apic"."""
    from jaxmpm import Body, Boundaries, Grid, Numerics, Probe, Rectangle, Scene

    cell = 1.0 / cells
    dt = 0.4 * cell / 40.0            # c_p = 36.7 m/s for these moduli: CFL about 0.37
    return Scene(
        name=f"elastic_block_{cells}",
        grid=Grid(size=(1.0, 1.0), cell=cell, boundaries=Boundaries("slip", "slip", "fixed", "free")),
        materials={"block": block_material(material)},
        bodies=(Body("block", "block", Rectangle((0.25, 0.0), (0.75, 0.5))),),
        duration=dt * steps,
        dt=dt,
        output_every=dt * min(steps, STEPS_PER_CALL),
        numerics=Numerics(shape=shape, transfer=transfer, ppc=2, flip=0.99, update="musl", dtype=dtype),
        probes=(
            Probe("top", "displacement", at=(0.5, 0.5)),
            Probe("centre_of_mass", "body_displacement", body="block"),
        ),
    )


def machine_info() -> dict:
    import jax
    import jaxlib

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = "unknown"
    try:
        kib = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1))
        memory = f"{kib / 2**20:.0f} GiB"
    except (OSError, AttributeError):
        pass
    try:
        commit = subprocess.run(
            ["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True, text=True
        ).stdout.strip()
    except OSError:
        commit = "unknown"
    return {
        "date": datetime.date.today().isoformat(),
        "cpu": cpu,
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "memory": memory,
        "python": platform.python_version(),
        "jax": f"{jax.__version__} (jaxlib {jaxlib.__version__}, {jax.default_backend()})",
        "commit": commit or "unknown",
        "load": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan"),
    }


def write_section(begin: str, end: str, body: str, doc: Path = DOC):
    """Replace (or append) the part of docs/benchmarks.md between the markers begin and end."""
    doc.parent.mkdir(parents=True, exist_ok=True)
    section = f"{begin}\n{body}\n{end}"
    current = doc.read_text() if doc.exists() else (
        "# Benchmarks\n\nFigures written by the scripts in `benchmarks/`; each script updates its own section.\n"
    )
    if begin in current and end in current:
        head, rest = current.split(begin, 1)
        doc.write_text(head + section + rest.split(end, 1)[1])
    else:
        doc.write_text(current.rstrip() + "\n\n" + section + "\n")
