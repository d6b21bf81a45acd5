"""visvec: camera attitude sensor for air-bearing spacecraft simulators.

The public API is in :mod:`visvec.api`.
"""

__version__ = "0.1.0"
