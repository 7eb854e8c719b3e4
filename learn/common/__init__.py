"""Pieces shared by the learners.

``mesh`` (edges, boundaries, uniform Laplacians), ``smoothing`` (boundary-aware
Laplacian smoothing, TailorNet's frequency split), ``mlp`` (TailorNet's MLP), ``losses``
(L1 displacement loss, per-vertex error in mm), ``collision`` (Warp signed distances and
the collision-rate metric), ``postprocess`` (Laplacian-preserving push-out of body
penetrations), ``skinning`` (posing callables built from a ``simulate.body`` model).
"""
