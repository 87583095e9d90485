"""shapecorr: unsupervised deformable 3D shape correspondence and interpolation."""

from shapecorr.errors import ShapeCorrError

__version__ = "0.1.0"

__all__ = ["ShapeCorrError", "__version__"]
