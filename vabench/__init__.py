"""vabench: VA-Bench on MuJoCo MJX, built for throughput.

See README.md for the set-up and ../shared/DESIGN.md (kept in docs/DESIGN.md) for the map.
"""

__version__ = "0.1.0"
