"""Numerical precision: estim computes in float64, always.

Importing estim switches JAX's 64-bit mode on (``jax_enable_x64``), because event times
and their sensitivities lose most of their digits in float32. If 64-bit mode is switched
off afterwards, every entry point raises instead of returning float32 results.
"""

import jax

jax.config.update("jax_enable_x64", True)


def require_x64() -> None:
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "estim needs JAX's 64-bit mode, which was switched off after importing estim; "
            "run jax.config.update('jax_enable_x64', True)"
        )


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Keep compiled programs on disk, so a new process skips most of JAX's compile time.

    Uses JAX's persistent compilation cache at ``path`` (default ``$ESTIM_CACHE_DIR`` or
    ``~/.cache/estim/jax``). Leaves an existing JAX cache setting alone; ``ESTIM_NO_CACHE=1``
    turns it off. The ``estim`` command calls this; library users may. Returns the directory
    used, or None.
    """
    import os

    if os.environ.get("ESTIM_NO_CACHE") == "1":
        return None
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    path = path or os.environ.get("ESTIM_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "estim", "jax"
    )
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path
