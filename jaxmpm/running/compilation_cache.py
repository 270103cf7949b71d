"""Compiled programs kept on disk, so that a scene compiled once loads quickly the next time.

Compiling a scene's step takes 2–5 s on a CPU, a calibration's gradient or Jacobian 10–45 s.
The program depends only on what is static in the scene (grid, bodies, numerics, which
parameters are fitted), never on parameter values, so a scene run again, or calibrated
again against other observations or from other starts, compiles the same programs. JAX's
persistent compilation cache stores each compiled program on disk, keyed by the program,
the compiler options, the JAX and XLA versions and the device, and loads it when the key
matches. A changed program simply misses and compiles.

`jaxmpm run` and `jaxmpm calibrate` use the cache by default. In Python, call
`jaxmpm.use_compilation_cache()` before the first simulation compiles.

Directory: $JAXMPM_CACHE_DIR, else $XDG_CACHE_HOME/jaxmpm/xla, else ~/.cache/jaxmpm/xla.
`JAXMPM_CACHE_DIR=off` turns it off. A cache directory you set for JAX yourself
(JAX_COMPILATION_CACHE_DIR or jax.config) is left as it is. Entries are 0.1–2 MB each
and are never evicted (JAX's size cap needs the filelock package, which jaxmpm does not
depend on); the directory can be deleted at any time.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

OFF = ("off", "none", "0", "false", "")


def cache_directory(environment=None) -> Path | None:
    """The cache directory the environment asks for (see the module docstring), or None when
    it is turned off."""
    environment = os.environ if environment is None else environment
    chosen = environment.get("JAXMPM_CACHE_DIR")
    if chosen is not None:
        return None if chosen.strip().lower() in OFF else Path(chosen).expanduser()
    base = environment.get("XDG_CACHE_HOME") or Path(environment.get("HOME", Path.home())) / ".cache"
    return Path(base) / "jaxmpm" / "xla"


def use_compilation_cache(directory=None) -> Path | None:
    """Keep compiled programs in `directory` (default `cache_directory()`); returns the
    directory in use, or None when the cache is off or the directory cannot be created (a
    warning says why; nothing else changes, programs are then compiled every time)."""
    import jax

    if jax.config.jax_compilation_cache_dir:          # set by the user for JAX: theirs
        return Path(jax.config.jax_compilation_cache_dir)
    directory = cache_directory() if directory is None else Path(directory)
    if directory is None:
        return None
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        warnings.warn(f"compilation cache {str(directory)!r} is not usable ({error.strerror}): compiling "
                      "every time (set JAXMPM_CACHE_DIR to another directory, or to off).", stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(directory))
    return directory
