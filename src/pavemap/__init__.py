"""pavemap: 3D road defect mapping from driving video."""

__version__ = "0.1.0"
