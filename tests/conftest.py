"""Tests run in float64 (enabled here explicitly; the library never flips it)."""
import jax

jax.config.update("jax_enable_x64", True)
