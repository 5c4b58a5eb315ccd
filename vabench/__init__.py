"""vabench: the VA-Bench benchmark built for throughput (MuJoCo Warp on GPUs, C MuJoCo on CPUs).

README.md is the front door; docs/DESIGN.md the map.
"""

__version__ = "0.1.0"
