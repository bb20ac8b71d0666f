"""geometry: the neutral head mesh and the Gaussians seeded from it.

Owns: tetrahedral grids, differentiable marching tetrahedra (DMTet), the SDF MLP and its fitting to
multi-view data, pymeshlab cleanup, mesh inspection/comparison, Gaussian initialization, and the
``python -m geometry`` CLI.

May import: toolkit, render. open3d and pymeshlab are imported lazily inside the functions that use them.
"""
