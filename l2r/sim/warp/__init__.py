"""The runner on MuJoCo Warp: the port's force elements as float32 Warp kernels over many worlds
(one module per numba module of `l2r.sim`), stepped around MuJoCo Warp's step (`physics.py`),
and `l2r/RunWarp-v0` (`env.py`)."""

import logging

import warp as wp

# Warp prints a line for every kernel module it loads, on stdout, where l2r's commands print
# their JSON: only its warnings and errors.
wp.config.log_level = max(wp.config.log_level, logging.WARNING)
