"""clrefract: portable OpenCL engine for neural inverse rendering of refractive media."""

__version__ = "0.1.0"
