"""Geometry core: pure functions on meshes, one module per concept.

Precomputation (numpy in/out, float64): ``laplace_beltrami`` (Laplacian, mass, eigenbasis), ``descriptors``
(HKS, WKS), ``shot_descriptor``, ``geodesics``, ``sampling``, ``remeshing``. Differentiable (torch): ``shells``
(spectral coefficients, smooth shells), ``normals``. Import the module you need
(``from shapecorr.geometry.laplace_beltrami import eigenbasis``): the package itself imports nothing, so that
``import shapecorr.geometry.mesh`` stays light (no libigl, potpourri3d or torch behind it).
"""
