"""Plot the final deposit of a column-collapse run and compare its runout with scaling laws.

    jaxmpm run examples/column_collapse.toml -o column_collapse.h5
    python examples/plot_column_collapse.py column_collapse.h5 [-o column_collapse.png]

Runout (L_inf - L0) / L0 = lambda a for aspect ratio a = H0 / L0 below the transition:
lambda = 1.2 (Lube et al. 2005) to 1.8 (Lajeunesse et al. 2005) (docs/validation.md §6).
The deposit edge is the outermost point plus half a point spacing.
"""

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxmpm  # noqa: E402

SCALING_LAWS = {"Lube et al. 2005": 1.2, "Lajeunesse et al. 2005": 1.8}


def deposit_measures(initial, final, spacing):
    """(L0, H0, L_inf, H_inf) [m] from initial and final point positions (N, 2)."""
    half = 0.5 * spacing
    return (
        initial[:, 0].max() + half,
        initial[:, 1].max() + half,
        final[:, 0].max() + half,
        final[:, 1].max() + half,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", help="HDF5 file of a column_collapse run")
    parser.add_argument("-o", "--output", default="column_collapse.png")
    arguments = parser.parse_args()

    result = jaxmpm.Result.load(arguments.result)
    scene = jaxmpm.Scene.from_toml(result.scene_toml)
    body = scene.bodies[0].name
    positions = result.snapshots[body]["x"]
    spacing = scene.grid.cell / scene.numerics.ppc
    length0, height0, length, height = deposit_measures(positions[0], positions[-1], spacing)
    aspect = height0 / length0
    runout = (length - length0) / length0

    figure, axes = plt.subplots(figsize=(9, 3.2))
    axes.scatter(*positions[0].T, s=2, c="0.8", label="initial column")
    strain = result.snapshots[body].get("plastic_strain")
    colours = None if strain is None else strain[-1]
    shown = axes.scatter(*positions[-1].T, s=2, c=colours, cmap="viridis", label="final deposit")
    if colours is not None:
        figure.colorbar(shown, ax=axes, label="equivalent plastic strain")
    for name, factor in SCALING_LAWS.items():
        edge = length0 * (1.0 + factor * aspect)
        axes.axvline(edge, ls="--", lw=1, color="k" if factor < 1.5 else "r", label=f"{name}: {edge:.3f} m")
    axes.set_aspect("equal")
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")
    axes.set_title(
        f"{scene.name} at t = {result.time[-1]:.2f} s: a = {aspect:.2f}\n"
        f"runout (L - L0)/L0 = {runout:.2f} = {runout / aspect:.2f} a, H_final / H0 = {height / height0:.3f}",
        fontsize=10,
    )
    axes.legend(loc="upper right", fontsize=7, markerscale=4)
    figure.tight_layout()
    figure.savefig(arguments.output, dpi=150)
    print(f"runout (L - L0)/L0 = {runout:.3f} = {runout / aspect:.2f} a; "
          f"published {min(SCALING_LAWS.values()):.1f} a to {max(SCALING_LAWS.values()):.1f} a")
    print(f"final height / initial height = {height / height0:.3f}")
    print(f"wrote {arguments.output}")


if __name__ == "__main__":
    main()
