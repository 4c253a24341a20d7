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
