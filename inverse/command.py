"""`jaxmpm calibrate CONFIG.toml`: the calibration command, which inverse adds to the `jaxmpm`
command (entry point group `jaxmpm.commands` in pyproject.toml; jaxmpm does not import inverse),
and the calibration file as a kind of file `jaxmpm plot` draws (group `jaxmpm.file_kinds`).

    jaxmpm calibrate CONFIG.toml [-o FIT.h5] [--resume] [--keep-checkpoint] [--quiet]
"""

from __future__ import annotations

import sys

from jaxmpm.cli import output_path


class CalibrateCommand:
    help = "fit scene parameters to observed probe histories"

    @staticmethod
    def add_arguments(parser):
        parser.add_argument("config", help="calibration file (TOML; keys: docs/calibration_reference.md)")
        parser.add_argument("-o", "--output", help="fit HDF5 file (default: CONFIG name with .h5)")
        parser.add_argument("--resume", action="store_true", help="continue from OUTPUT.checkpoint.npz")
        parser.add_argument("--keep-checkpoint", action="store_true",
                            help="keep OUTPUT.checkpoint.npz after the fit is written (default: remove it)")
        parser.add_argument("--quiet", action="store_true", help="no progress bar")

    @staticmethod
    def run(arguments) -> int:
        import jax

        jax.config.update("jax_enable_x64", True)
        import jaxmpm
        from inverse.calibrate import calibrate
        from inverse.config import load_calibration

        jaxmpm.use_compilation_cache()
        config = load_calibration(arguments.config)
        output = output_path(arguments.output, arguments.config)
        checkpoint = output.with_name(output.name + ".checkpoint.npz")
        options = dict(config.options)
        name = options.pop("name")
        try:
            fit = calibrate(config.simulations(), fit=config.fit, optimizer=name, checkpoint=checkpoint,
                            resume=arguments.resume, progress=not arguments.quiet, **options)
        except KeyboardInterrupt:
            print(f"jaxmpm: interrupted; resume with --resume (checkpoint {checkpoint})", file=sys.stderr)
            return 130
        except jaxmpm.SimulationError as error:
            kept = f" (progress kept in {checkpoint}; resume with --resume)" if checkpoint.exists() else ""
            print(f"jaxmpm: {error}{kept}", file=sys.stderr)
            return 1
        fit.save(output)
        print(fit.summary())
        print(f"wrote {output}")
        if arguments.keep_checkpoint:
            print(f"kept the checkpoint {checkpoint}")
        else:
            checkpoint.unlink(missing_ok=True)      # the fit is written: the checkpoint has served
        return 0


CALIBRATE = CalibrateCommand()


class CalibrationFile:
    """The calibration result as a kind of file `jaxmpm plot` draws (jaxmpm.cli.plugged_file_kind)."""

    description = "a calibration result (`jaxmpm calibrate`)"
    how_to_open = "or open it with inverse.Fit.load in Python"

    @staticmethod
    def claims(file) -> bool:
        from inverse.fit_file import is_fit_file

        return is_fit_file(file)

    @staticmethod
    def plot(path, output):
        import matplotlib.pyplot as plt

        from inverse.fit import Fit

        plt.close(Fit.load(path).plot(output))


CALIBRATION_FILE = CalibrationFile()
